"""Depth images to point clouds (pinhole back-projection), vectorised.

``points_camera_m`` are in the optical camera frame (x right, y down, z forward). Invalid depth
(0, NaN, inf, outside [min, max]) never becomes a point.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from semmap.types import CameraIntrinsics


def valid_depth_mask(depth_m: NDArray[np.floating], min_m: float, max_m: float) -> NDArray[np.bool_]:
    """(H, W) True where depth is finite and within [min_m, max_m] (and > 0)."""
    d = np.asarray(depth_m)
    # NaN fails every comparison and +inf fails a finite upper bound, so two comparisons
    # decide validity (this runs on every box of every frame).
    with np.errstate(invalid="ignore"):
        low = d > 0 if min_m <= 0 else d >= min_m
        high = d <= max_m if np.isfinite(max_m) else np.isfinite(d)
        return low & high


def backproject(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    min_m: float = 0.0,
    max_m: float = np.inf,
    window_px: tuple[int, int, int, int] | None = None,
    stride_px: int = 1,
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Back-project valid depth pixels to 3D.

    ``window_px`` = (u0, v0, u1, v1), half-open, limits the work to a box (e.g. a detection).
    ``stride_px`` subsamples rows and columns. Returns ``(points_camera_m (N, 3) float32,
    pixels_uv (N, 2) int64)``: each point with the pixel it came from.
    """
    pts, uv = backproject_rows(depth_m, intrinsics, min_m, max_m, window_px, stride_px)
    return np.ascontiguousarray(pts.T), np.ascontiguousarray(uv.T)


def backproject_rows(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    min_m: float = 0.0,
    max_m: float = np.inf,
    window_px: tuple[int, int, int, int] | None = None,
    stride_px: int = 1,
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """:func:`backproject` with one row per coordinate: ``(points_camera_m (3, N) float32,
    pixels_uv (2, N) int64)``, C-contiguous. Per-coordinate work (a transform into the map,
    a height filter) then reads and writes contiguous rows, where on (N, 3) it strides."""
    d = np.asarray(depth_m)
    H, W = d.shape
    if (W, H) != (intrinsics.width_px, intrinsics.height_px):
        raise ValueError(
            f"depth image is {W}x{H} but intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}"
        )
    u0, v0, u1, v1 = window_px if window_px is not None else (0, 0, W, H)
    u0, v0 = max(0, int(u0)), max(0, int(v0))
    u1, v1 = min(W, int(u1)), min(H, int(v1))
    if u1 <= u0 or v1 <= v0:
        return np.zeros((3, 0), np.float32), np.zeros((2, 0), np.int64)
    sub = d[v0:v1:stride_px, u0:u1:stride_px]
    ok = valid_depth_mask(sub, min_m, max_m)
    vv, uu = np.nonzero(ok)
    z = sub[vv, uu].astype(np.float32)
    # Normalised image coordinates per used column / row, then one product per axis.
    xn = ((np.arange(u0, u1, stride_px) - intrinsics.cx_px) / intrinsics.fx_px).astype(np.float32)
    yn = ((np.arange(v0, v1, stride_px) - intrinsics.cy_px) / intrinsics.fy_px).astype(np.float32)
    pts = np.empty((3, len(z)), np.float32)
    np.multiply(xn[uu], z, out=pts[0])
    np.multiply(yn[vv], z, out=pts[1])
    pts[2] = z
    uv = np.empty((2, len(z)), np.int64)
    np.multiply(uu, stride_px, out=uv[0])
    uv[0] += u0
    np.multiply(vv, stride_px, out=uv[1])
    uv[1] += v0
    return pts, uv
