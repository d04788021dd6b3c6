"""What one camera frame could see.

:class:`CameraView` tells whether a map point should have been visible in a frame: a miss
there is negative evidence for the object map.

The rest says which sides of an observed footprint the field of view drew, not the object. A
table running out of the image has a footprint bounded on one side by where the depth image
ends. That side is straight, often long, and at an angle to the object's own edges, so a
least-perimeter rectangle fitted to such a view turns towards it. This module marks each edge
of an observation's footprint polygon as *cut* when the object's points along it lie on the
border of the depth image, and :class:`EdgeDirections` keeps, per object, how much footprint
edge length was seen and how much was cut in each direction, so the map's rectangle can take
the direction of the object's own edges instead (see :mod:`semmap.object_state`).

Only the field of view counts: an edge whose outside is hidden behind another object or by the
object itself is still the object's edge direction more often than not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from semmap.frames import Transform
from semmap.pointcloud import project_map_points, valid_depth_mask
from semmap.types import CameraIntrinsics

__all__ = ["DIRECTION_BINS", "CameraView", "EdgeDirections", "cut_edges", "depth_frame_px"]

#: A row or column with valid depth in at least this share of its pixels is inside the depth
#: image (a registered depth image has invalid bands along its borders).
FRAME_MIN_VALID_FRAC = 0.1
#: Directions are kept modulo 90 deg (a rectangle's sides) in bins this wide.
DIRECTION_BINS = 90
#: The seen length of a direction counts the bins this many either side of it (a straight
#: edge seen in several views, through voxels, scatters over a few degrees).
SMOOTH_BINS = 3
#: Views cut by the field of view by at least this much outline (metres) steer the rectangle:
#: a few short cut edges never do.
MIN_CUT_LENGTH_M = 0.2
#: The measured depth behind a point is the median of the valid pixels within this many
#: pixels of its projection (a lone noisy or flying pixel does not decide).
_PATCH_HALF_PX = 2


@dataclass(frozen=True)
class CameraView:
    """What one frame could see: for "should be visible but is not" (negative evidence).

    ``depth_m``: (H, W) metres, 0/NaN invalid. ``T_map_camera``: (4, 4). Points beyond
    ``depth_range_m`` or within ``margin_px`` of the image border are not expected to be seen.
    """

    depth_m: NDArray[np.floating]
    intrinsics: CameraIntrinsics
    T_map_camera: Transform
    depth_range_m: tuple[float, float] = (0.3, 6.0)
    tolerance_m: float = 0.3
    margin_px: int = 10

    def expects_visible(self, points_map_m: NDArray[np.floating],
                        tolerance_m: float | None = None) -> NDArray[np.bool_]:
        """(N,) True where a map point (N, 3) projects inside the image, within range, and the
        measured depth there (median of a 5x5 patch) is not nearer than the point by more than
        ``tolerance_m`` (None: the view's). Pixels without valid depth are not evidence either
        way (False)."""
        pts = np.asarray(points_map_m, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(pts), dtype=bool)
        if len(pts) == 0:
            return out
        K = self.intrinsics
        u, v, z = project_map_points(pts, K, self.T_map_camera)
        in_range = (z > 0.0) & (z >= self.depth_range_m[0]) & (z <= self.depth_range_m[1])
        m = max(self.margin_px, _PATCH_HALF_PX)  # the patch lies inside the image
        inside = np.flatnonzero(in_range & (u >= m) & (u < K.width_px - m) & (v >= m) & (v < K.height_px - m))
        if len(inside) == 0:
            return out
        d = np.asarray(self.depth_m)
        # One flat gather of every point's patch: this runs on each cell of each object in view.
        offsets = np.arange(-_PATCH_HALF_PX, _PATCH_HALF_PX + 1)
        flat_offsets = (offsets[:, None] * d.shape[1] + offsets[None, :]).reshape(-1)
        centre = v[inside].astype(np.int64) * d.shape[1] + u[inside].astype(np.int64)
        patch = np.take(d.reshape(-1), centre[:, None] + flat_offsets[None, :])
        valid = valid_depth_mask(patch, self.depth_range_m[0], self.depth_range_m[1])
        n_valid = valid.sum(axis=1)
        median = np.full(len(inside), np.nan)
        # Rows with every pixel valid (most): their middle value, by partition.
        full = n_valid == patch.shape[1]
        mid = patch.shape[1] // 2
        median[full] = np.partition(patch[full], mid, axis=1)[:, mid]
        some = np.flatnonzero(~full & (n_valid > 0))
        if len(some):
            rest = np.where(valid[some], patch[some], np.inf)  # sorted last: the median is among the first n_valid
            srt = np.sort(rest, axis=1)  # (np.nanmedian is ten times slower on many short rows)
            n = n_valid[some]
            median[some] = 0.5 * (srt[np.arange(len(some)), (n - 1) // 2].astype(np.float64)
                                  + srt[np.arange(len(some)), n // 2].astype(np.float64))
        tol = self.tolerance_m if tolerance_m is None else tolerance_m
        seen = n_valid > 0
        out[inside[seen]] = median[seen] >= z[inside[seen]] - tol
        return out


def depth_frame_px(depth_m: NDArray[np.floating], min_m: float, max_m: float) -> tuple[int, int, int, int]:
    """(u0, v0, u1, v1), inclusive: the rows and columns of the depth image that hold valid
    depth (in ``[min_m, max_m]``) in at least ``FRAME_MIN_VALID_FRAC`` of their pixels; the
    whole image when none do."""
    d = np.asarray(depth_m)
    h, w = d.shape
    # Every 4th row says which columns are valid and every 4th column which rows: the shares
    # need no more, and the full image costs four times as much.
    cols = np.flatnonzero(valid_depth_mask(d[::4], min_m, max_m).mean(axis=0) >= FRAME_MIN_VALID_FRAC)
    rows = np.flatnonzero(valid_depth_mask(d[:, ::4], min_m, max_m).mean(axis=1) >= FRAME_MIN_VALID_FRAC)
    if len(cols) == 0 or len(rows) == 0:
        return 0, 0, w - 1, h - 1
    return int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])


def cut_edges(
    footprint_xy_m: NDArray[np.float64], voxels_map_m: NDArray[np.float64], intrinsics: CameraIntrinsics,
    T_map_camera: Transform, frame_px: tuple[int, int, int, int], voxel_size_m: float, stride_px: int = 1,
) -> NDArray[np.bool_]:
    """(M,) per edge k (vertex k to k+1) of a counter-clockwise footprint (M, 2): True where
    most of the object's voxels (K, 3) along the edge (within two voxels inside it) project
    onto the border of the depth image ``frame_px`` (u0, v0, u1, v1): the view ends there, not
    the object. "Onto the border" allows for the sampling (``stride_px``) and a voxel's size
    in pixels at its depth."""
    poly = np.asarray(footprint_xy_m, dtype=np.float64)
    m = len(poly)
    vox = np.asarray(voxels_map_m, dtype=np.float64)
    if m < 3 or len(vox) == 0:
        return np.zeros(m, dtype=bool)
    u, v, z = project_map_points(vox, intrinsics, T_map_camera)
    slack_px = 2.0 * stride_px + voxel_size_m * intrinsics.fx_px / np.maximum(z, 1e-3)
    u0, v0, u1, v1 = frame_px
    on_border = (z <= 0.0) | (u <= u0 + slack_px) | (u >= u1 - slack_px) | (v <= v0 + slack_px) | (v >= v1 - slack_px)
    if not on_border.any():
        return np.zeros(m, dtype=bool)  # most objects: wholly in view
    a = poly
    d = np.roll(poly, -1, axis=0) - a
    length = np.linalg.norm(d, axis=1)
    ok = length > 1e-9
    outward = np.zeros_like(d)
    outward[ok] = np.column_stack([d[ok, 1], -d[ok, 0]]) / length[ok, None]  # right of a CCW edge
    rel = vox[None, :, :2] - a[:, None, :]  # (M, K, 2)
    t = np.einsum("mkj,mj->mk", rel, d) / np.maximum(length, 1e-9)[:, None] ** 2
    inside_by_m = -np.einsum("mkj,mj->mk", rel, outward)
    band = (t >= 0.0) & (t <= 1.0) & (inside_by_m <= 2.0 * voxel_size_m)
    n_band = band.sum(axis=1)
    n_border = (band & on_border[None, :]).sum(axis=1)
    return ok & (n_band > 0) & (2 * n_border > n_band)


@dataclass
class EdgeDirections:
    """Per object: footprint edge length (metres) seen and cut by the field of view, per
    direction modulo 90 deg (``DIRECTION_BINS`` bins; rows 0 seen, 1 cut)."""

    length_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros((2, DIRECTION_BINS)))

    def add_view(self, footprint_xy_m: NDArray[np.float64], cut: NDArray[np.bool_]) -> None:
        """Add one view's footprint (M, 2) and its edges' cut flags (M,)."""
        poly = np.asarray(footprint_xy_m, dtype=np.float64)
        d = np.roll(poly, -1, axis=0) - poly
        index = np.asarray(cut, dtype=np.int64) * DIRECTION_BINS + _bins(d)
        self.length_m = self.length_m + np.bincount(index, weights=np.linalg.norm(d, axis=1),
                                                    minlength=2 * DIRECTION_BINS).reshape(2, DIRECTION_BINS)

    def merge(self, other: EdgeDirections) -> None:
        """Fold another object's edges into this one (two objects found to be one)."""
        self.length_m = self.length_m + other.length_m

    def rectangle_direction_rad(self) -> float | None:
        """The direction (radians, modulo 90 deg) a footprint rectangle's sides should take, or
        None to leave it to the least-perimeter fit: where the field of view cut the views'
        outlines by at least ``MIN_CUT_LENGTH_M``, the direction of most seen edge length.

        A least-perimeter rectangle around a cut outline turns towards the cut; the object's
        own edges, where seen, run along its sides."""
        seen, cut = self.length_m
        if cut.sum() < MIN_CUT_LENGTH_M or not seen.any():
            return None
        offsets = np.arange(-SMOOTH_BINS, SMOOTH_BINS + 1)
        window = (np.arange(DIRECTION_BINS)[:, None] + offsets[None, :]) % DIRECTION_BINS  # (B, 2S+1)
        support = seen[window].sum(axis=1)
        peak = int(np.argmax(support))
        w = seen[window[peak]]
        centre_bin = peak + 0.5 + float(np.dot(w, offsets)) / float(w.sum())
        return centre_bin / DIRECTION_BINS * (math.pi / 2)


def _bins(directions_xy: NDArray[np.float64]) -> NDArray[np.int64]:
    ang = np.mod(np.arctan2(directions_xy[:, 1], directions_xy[:, 0]), math.pi / 2)
    return np.minimum((ang / (math.pi / 2) * DIRECTION_BINS).astype(np.int64), DIRECTION_BINS - 1)
