"""A depth image turned into a 2D scan of one height band (the grid's input).

For each image column the scan keeps the nearest obstacle point whose height lies inside the
band (a virtual 2D lidar at flight altitude, as the reference design derives Cartographer's
scan from the point cloud). Free space is what valid rays crossed *inside the band*: from
where a ray enters the band to where it leaves it, ends, or meets the column's nearest
in-band obstacle. Rays with invalid depth (0, NaN, out of range) say nothing: a RealSense
returns 0 for "no echo", which must not clear the map.

The map-frame direction of every pixel is ``R @ [(u - cx)/fx, (v - cy)/fy, 1]``, so a point
is ``t + depth * direction`` without building an (N, 3) cloud first. Sampling, validity and
the dropout repairs run vectorised on the (subsampled) image; the per-ray work (nearest
in-band points, their support, the cluster mean, band entry and exit) runs in one
numba-compiled pass per column (:func:`_scan_columns`, cached as in
:mod:`semmap.clustering`), in the float32 arithmetic the vectorised version used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.costmap import VerticalBand
from semmap.errors import FrameError
from semmap.pointcloud import valid_depth_mask
from semmap.types import CameraIntrinsics


@dataclass(frozen=True, eq=False)
class BandScan:
    """One fan of rays in a horizontal frame, one ray per used image column, ordered by bearing.

    The frame is the one the extraction was given: the map frame for the occupancy grid, the
    gravity-aligned body frame for the SLAM (:func:`semmap.slam.scan2d.level_scan_from_depth`,
    moved into a submap by :func:`semmap.slam.pose2d.transform_scan`).

    ``origin_xy_m``: (2,) sensor position. ``near_xy_m``/``far_xy_m``: (N, 2) start and end of
    each ray's free part inside the band. ``is_hit``: (N,) the ray meets an obstacle, at
    ``hit_xy_m`` (N, 2) (at or just beyond ``far_xy_m``; its nearest point has height
    ``hit_z_m``, NaN when no hit). ``valid``: (N,) the ray carries information (some valid
    depth crossed the band).
    """

    stamp_s: float
    band: VerticalBand
    origin_xy_m: NDArray[np.float64]
    near_xy_m: NDArray[np.float64]
    far_xy_m: NDArray[np.float64]
    hit_xy_m: NDArray[np.float64]
    is_hit: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    hit_z_m: NDArray[np.float64]

    @property
    def hits_xy_m(self) -> NDArray[np.float64]:
        """(K, 2) obstacle points."""
        return self.hit_xy_m[self.is_hit & self.valid]

    @property
    def n_rays(self) -> int:
        return int(len(self.valid))

    @classmethod
    def from_points(cls, points_xy_m: NDArray[np.floating], origin_xy_m: tuple[float, float] = (0.0, 0.0),
                    stamp_s: float = 0.0) -> "BandScan":
        """Rays from ``origin_xy_m`` to each of the (N, 2) points, every point a hit. Points
        should be ordered by bearing (consecutive rays bound the free polygon). Their heights
        are unknown: the band is unbounded and ``hit_z_m`` NaN."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise FrameError("scan points must be finite")
        o = np.asarray(origin_xy_m, dtype=np.float64).reshape(2)
        n = len(pts)
        return cls(stamp_s, VerticalBand(-math.inf, math.inf), o, np.tile(o, (n, 1)), pts.copy(), pts.copy(),
                   np.ones(n, bool), np.ones(n, bool), np.full(n, np.nan))


def fill_dropouts(
    depth_m: NDArray[np.float32], valid: NDArray[np.bool_], rows: int,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Fill invalid pixels that have valid depth within ``rows`` rows both above and below
    (same column) with the nearer of the two nearest values: a dropout sandwiched in a
    surface or at a thin edge. Pixels at the border of the valid region (beyond the sensor's
    range, the image edge) stay invalid. ``depth_m``/``valid``: (h, w)."""
    # Only the invalid pixels (a few per cent) are looked at: their ``rows`` neighbours
    # above and below are gathered as (rows, n) and reduced across the pixels.
    rr, cc = np.nonzero(~valid)
    out_d, out_v = np.array(depth_m, copy=True), np.array(valid, copy=True)
    if not len(rr) or rows < 1:
        return out_d, out_v
    h = valid.shape[0]
    ks = np.arange(1, rows + 1)[:, None]  # (rows, 1)
    inf = np.float32(np.inf)
    nearest = []
    for nb in (rr[None, :] - ks, rr[None, :] + ks):  # (rows, n) above, below
        inside = (nb >= 0) & (nb < h)
        nb = np.clip(nb, 0, h - 1)
        ok = inside & valid[nb, cc]
        nearest.append(np.where(ok, depth_m[nb, cc], inf).min(axis=0))
    above, below = nearest
    fill = np.isfinite(above) & np.isfinite(below)
    out_d[rr[fill], cc[fill]] = np.minimum(above, below)[fill]
    out_v[rr[fill], cc[fill]] = True
    return out_d, out_v


def recover_skipped(
    depth_m: NDArray[np.floating], sub: NDArray[np.float32], valid: NDArray[np.bool_],
    row_stride: int, col_stride: int, min_depth_m: float, max_depth_m: float,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Replace each invalid sample of the subsampled image ``sub`` (h, w) by the nearest valid
    depth among the full-resolution pixels its stride skipped (its ``row_stride`` x
    ``col_stride`` block of ``depth_m``), when there is one.

    A thin surface at band height (a 3 cm table top a few metres away) is one or two pixels
    tall, and a depth camera drops pixels at depth edges, which such a sliver is made of: a
    plain stride keeps it only when the sampled pixel happens to be on it and valid, and the
    rays of the other columns then pass under the top and clear its footprint. Valid samples
    are kept as they are (a block minimum would bias every surface towards the sensor); an
    invalid sample says nothing, so the block's nearest valid depth (the conservative choice
    at an edge, as :func:`fill_dropouts` takes) is better information in its place.
    """
    if row_stride <= 1 and col_stride <= 1:
        return sub, valid
    rr, cc = np.nonzero(~valid)
    if not len(rr):
        return sub, valid
    d = np.asarray(depth_m)
    H, W = d.shape
    # The block's pixels as (s * sc, n): the minimum then runs across the samples, one
    # vectorised pass per pixel of the block, instead of a short reduction per sample
    # (ten times the cost); a contiguous image is gathered by flat index.
    rows = np.minimum(rr[None, :] * row_stride + np.arange(row_stride)[:, None], H - 1)  # (s, n)
    cols = np.minimum(cc[None, :] * col_stride + np.arange(col_stride)[:, None], W - 1)  # (sc, n)
    rows_b = np.broadcast_to(rows[:, None, :], (row_stride, col_stride, len(rr))).reshape(-1, len(rr))
    cols_b = np.broadcast_to(cols[None, :, :], (row_stride, col_stride, len(rr))).reshape(-1, len(rr))
    if d.flags.c_contiguous:
        block = d.reshape(-1).take(rows_b * W + cols_b)  # (s * sc, n)
    else:
        block = d[rows_b, cols_b]
    block = block.astype(np.float32, copy=False)
    block = np.where(valid_depth_mask(block, min_depth_m, max_depth_m), block, np.float32(np.inf))
    nearest = block.min(axis=0)
    found = np.isfinite(nearest)
    out, ok = sub.copy(), valid.copy()
    out[rr[found], cc[found]] = nearest[found]
    ok[rr[found], cc[found]] = True
    return out, ok


def extract_band_scan(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    T_map_camera: NDArray[np.float64],
    band: VerticalBand,
    min_depth_m: float = 0.3,
    max_depth_m: float = 6.0,
    stride_px: int = 2,
    min_hit_points: int = 2,
    range_tolerance_m: float = 0.05,
    range_tolerance_per_m2: float = 0.01,
    fill_px: int = 4,
    free_sigma: float = 1.0,
    cluster_tol: float = 1.0,
    recentre_hit: bool = False,
    stamp_s: float = 0.0,
    column_stride_px: int | None = None,
    recover_px: bool = True,
) -> BandScan:
    """Extract the band scan of one depth image.

    ``depth_m``: (H, W) metres along the optical axis. ``T_map_camera``: (4, 4) optical camera
    to map (z up, floor at z = 0); ``band`` in map-frame metres above the floor.
    ``stride_px`` subsamples rows, ``column_stride_px`` columns (default: the same), so
    there is one ray per used column; with ``recover_px`` an invalid sample takes the nearest
    valid depth of the pixels its strides skipped (:func:`recover_skipped`). Invalid pixels
    with valid depth within
    ``fill_px`` rows above and below take the nearer: sensors drop pixels at depth edges, and
    a dropped table edge must not let the rays under the table clear its footprint.
    ``min_hit_points``: a column's nearest in-band point is an obstacle only with this many
    points (itself included) within the range tolerance among the column's next point and the
    two neighbouring columns' nearest, so a single flying pixel is not a wall.
    The obstacle is placed at the mean range of the column's nearest cluster, the points
    within ``cluster_tol * tol`` of it with ``tol = range_tolerance_m +
    range_tolerance_per_m2 * r**2`` (about three sigma of a D455-like depth noise): the
    nearest point alone is biased towards the sensor. With ``recentre_hit`` the obstacle moves
    once more, to the mean range of the points within ``tol`` either side of that mean: the
    cluster's window starts at its nearest point, so its mean still sits about half a sigma
    short of the surface. A map may keep that (it errs towards the vehicle); a scan matcher
    may not, because the bias grows with range squared and so turns a wall seen obliquely by
    an angle that changes with the viewpoint. Free space ends ``free_sigma`` noise sigmas
    (``tol / 3``) before the obstacle, or at the nearest point if that is farther.
    """
    d, T = _checked_frame(depth_m, intrinsics, T_map_camera)
    s = max(1, int(stride_px))
    sc = max(1, int(column_stride_px)) if column_stride_px is not None else s
    dep, valid = _subsampled_filled_depth(d, s, sc, min_depth_m, max_depth_m, fill_px, recover_px)
    return _band_scan_of_filled_depth(
        dep, valid, intrinsics, d.shape, s, sc, T, band, max(0, int(min_hit_points) - 1), range_tolerance_m,
        range_tolerance_per_m2, cluster_tol, free_sigma, recentre_hit, stamp_s,
    )


def _band_scan_of_filled_depth(
    dep: NDArray[np.float32], valid: NDArray[np.bool_], intrinsics: CameraIntrinsics, shape_px: tuple[int, ...],
    s: int, sc: int, T_map_camera: NDArray[np.float64], band: VerticalBand, min_support: int,
    range_tolerance_m: float, range_tolerance_per_m2: float, cluster_tol: float, free_sigma: float,
    recentre_hit: bool, stamp_s: float,
) -> BandScan:
    """The :class:`BandScan` of ``dep``, every ``s``-th row and ``sc``-th column of an image of
    ``shape_px`` (H, W), one ray per column from the compiled per-ray pass (:func:`_scan_columns`)."""
    H, W = shape_px
    us = np.arange(0, W, sc, dtype=np.float32)
    vs = np.arange(0, H, s, dtype=np.float32)
    xn = (us - np.float32(intrinsics.cx_px)) / np.float32(intrinsics.fx_px)  # (w,)
    yn = (vs - np.float32(intrinsics.cy_px)) / np.float32(intrinsics.fy_px)  # (h,)
    R = T_map_camera[:3, :3].astype(np.float32)
    tx, ty, tz = (float(v) for v in T_map_camera[:3, 3])
    w = dep.shape[1]
    near, far, hit_xy = np.empty((w, 2)), np.empty((w, 2)), np.empty((w, 2))
    is_hit, ray_valid, hit_z = np.empty(w, np.bool_), np.empty(w, np.bool_), np.empty(w)
    _scan_columns(
        dep, valid, xn, yn, R, tx, ty, tz, float(band.z_min_m), float(band.z_max_m),
        bool(band.z_min_m <= tz <= band.z_max_m), min_support,
        float(range_tolerance_m), float(range_tolerance_per_m2), float(cluster_tol), float(free_sigma),
        bool(recentre_hit), near, far, hit_xy, is_hit, ray_valid, hit_z,
    )
    return BandScan(
        stamp_s=stamp_s, band=band, origin_xy_m=np.array([tx, ty]),
        near_xy_m=near, far_xy_m=far, hit_xy_m=hit_xy, is_hit=is_hit & ray_valid, valid=ray_valid,
        hit_z_m=hit_z,
    )


def _checked_frame(
    depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: NDArray[np.float64]
) -> tuple[NDArray[np.floating], NDArray[np.float64]]:
    """The depth image and the pose as arrays, or a :class:`FrameError` naming what is wrong."""
    d = np.asarray(depth_m)
    if d.ndim != 2:
        raise FrameError(f"depth image must be (H, W), got shape {d.shape}")
    H, W = d.shape
    if (W, H) != (intrinsics.width_px, intrinsics.height_px):
        raise FrameError(
            f"depth image is {W}x{H} but intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}"
        )
    T = np.asarray(T_map_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FrameError(f"T_map_camera must be a finite (4, 4) transform, got shape {T.shape}")
    return d, T


def _subsampled_filled_depth(
    d: NDArray[np.floating], s: int, sc: int, min_depth_m: float, max_depth_m: float,
    fill_px: int, recover_px: bool,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The (h, w) depth at every ``s``-th row and ``sc``-th column (0 where invalid) and its
    validity, with skipped pixels recovered and dropouts filled as :func:`extract_band_scan`
    describes."""
    sub = d[::s, ::sc].astype(np.float32, copy=False)  # (h, w)
    valid = valid_depth_mask(sub, min_depth_m, max_depth_m)
    if recover_px:
        sub, valid = recover_skipped(d, sub, valid, s, sc, min_depth_m, max_depth_m)
    dep = np.where(valid, sub, np.float32(0.0))
    if fill_px > 0:
        dep, valid = fill_dropouts(dep, valid, max(1, int(round(fill_px / s))))
    return dep, valid

@numba.njit(cache=True)
def _f32(x: Any) -> Any:
    """Round to float32: numba evaluates float32 arithmetic in float64, and rounding each
    result back gives exactly the float32 operation (double rounding is innocuous for
    +, -, *, / and sqrt from 53 to 24 bits)."""
    return np.float32(x)


@numba.njit(cache=True, error_model="numpy")
def _scan_columns(
    dep: NDArray[np.float32], valid: NDArray[np.bool_], xn: NDArray[np.float32], yn: NDArray[np.float32],
    R: NDArray[np.float32], tx: float, ty: float, tz: float, band_lo: float, band_hi: float,
    sensor_in_band: bool, min_support: int, range_tol: float, range_tol_per_m2: float,
    cluster_tol: float, free_sigma: float, recentre_hit: bool,
    near: NDArray[np.float64], far: NDArray[np.float64], hit_xy: NDArray[np.float64],
    is_hit: NDArray[np.bool_], ray_valid: NDArray[np.bool_], hit_z: NDArray[np.float64],
) -> None:
    """The per-ray part of :func:`extract_band_scan` for the (h, w) filled depth ``dep``, one
    ray per column, compiled (numba, cached as in :mod:`semmap.clustering`): the same numbers
    as the vectorised numpy it replaces (float32 where that was float32, float64 where numpy
    promoted), in one pass per column instead of ~60 whole-image array operations.

    Writes, per column: ``near``/``far`` (w, 2) ends of the free part, ``hit_xy`` (w, 2),
    ``is_hit``, ``ray_valid`` (w,) and ``hit_z`` (w,) (NaN without a hit).
    """
    h, w = dep.shape
    f = _f32
    z0, z1, tz32 = f(band_lo), f(band_hi), f(tz)
    rt, rtp = f(range_tol), f(range_tol_per_m2)
    # Per pixel of one column: offsets from the sensor, height, range, band crossing.
    ox = np.empty(h, np.float32)
    oy = np.empty(h, np.float32)
    zc = np.empty(h, np.float32)
    rng = np.empty(h, np.float32)
    s_lo = np.empty(h, np.float32)
    s_hi = np.empty(h, np.float32)
    crosses = np.empty(h, np.bool_)
    hit_rng = np.empty((w, h), np.float32)
    first_row = np.zeros(w, np.int64)
    second_row = np.zeros(w, np.int64)
    r1 = np.empty(w, np.float32)
    r2 = np.empty(w, np.float32)
    # Pass 1 over all columns first: the neighbouring columns' nearest ranges are needed.
    _nearest_in_band(dep, valid, xn, yn, R, tz32, z0, z1, hit_rng, first_row, second_row, r1, r2)
    for c in range(w):
        any_cross = _column_rays(dep, valid, xn, yn, R, c, tz32, z0, z1, sensor_in_band,
                                 ox, oy, zc, rng, s_lo, s_hi, crosses)
        hit, hit_row, tol, r_hit = _obstacle_range(hit_rng, r1, r2, first_row, second_row, c, rt, rtp,
                                                   min_support, cluster_tol, recentre_hit)
        far_row, far_s, near_row, near_s, med_row = _free_ends_and_hit_row(
            hit_rng, c, rng, s_lo, s_hi, crosses, first_row[c], r1[c], hit, r_hit, tol, free_sigma, sensor_in_band)
        ray_valid[c] = any_cross or math.isfinite(r1[c])
        far[c, 0] = tx + np.float64(ox[far_row]) * far_s
        far[c, 1] = ty + np.float64(oy[far_row]) * far_s
        scale = r_hit / np.float64(rng[med_row]) if hit else 1.0
        if not math.isfinite(scale):
            scale = 1.0
        hit_xy[c, 0] = tx + np.float64(ox[med_row]) * scale
        hit_xy[c, 1] = ty + np.float64(oy[med_row]) * scale
        near[c, 0] = tx + np.float64(f(ox[near_row] * near_s))
        near[c, 1] = ty + np.float64(f(oy[near_row] * near_s))
        is_hit[c] = hit
        hit_z[c] = np.float64(zc[hit_row]) if hit else np.nan


@numba.njit(cache=True, error_model="numpy")
def _obstacle_range(
    hit_rng: NDArray[np.float32], r1: NDArray[np.float32], r2: NDArray[np.float32], first_row: NDArray[np.int64],
    second_row: NDArray[np.int64], c: int, rt: np.float32, rtp: np.float32, min_support: int,
    cluster_tol: float, recentre_hit: bool,
) -> tuple[bool, int, np.float32, float]:
    """Column ``c``'s obstacle: whether it has one, the row of its nearest point (the nearest
    in-band one if confirmed, else the second nearest), that point's range tolerance and the
    obstacle's range (the nearest cluster's mean, recentred if asked; 0 without a hit)."""
    f = _f32
    q1 = r1[c]
    confirmed = _nearest_confirmed(r1, r2, c, rt, rtp, min_support)
    r_near = q1 if confirmed else r2[c]
    hit = math.isfinite(r_near)
    hit_row = first_row[c] if confirmed else second_row[c]
    r_near_f = r_near if hit else np.float32(0.0)
    tol = f(rt + f(rtp * f(r_near_f * r_near_f)))
    r_hit = _cluster_mean_range(hit_rng, c, r_near_f, f(r_near_f + f(cluster_tol * tol))) if hit else 0.0
    if hit and recentre_hit:
        tol_hit = f(rt + f(rtp * f(np.float32(r_hit) * np.float32(r_hit))))
        r_hit = _cluster_mean_range(hit_rng, c, f(r_hit - tol_hit), f(r_hit + tol_hit))
    return hit, hit_row, tol, r_hit


@numba.njit(cache=True, error_model="numpy")
def _nearest_in_band(
    dep: NDArray[np.float32], valid: NDArray[np.bool_], xn: NDArray[np.float32], yn: NDArray[np.float32],
    R: NDArray[np.float32], tz32: np.float32, z0: np.float32, z1: np.float32, hit_rng: NDArray[np.float32],
    first_row: NDArray[np.int64], second_row: NDArray[np.int64], r1: NDArray[np.float32], r2: NDArray[np.float32],
) -> None:
    """Writes each pixel's horizontal range if in the band (else inf) to ``hit_rng`` (w, h),
    and each column's nearest and second-nearest in-band rows and ranges."""
    h, w = dep.shape
    f = _f32
    inf32 = np.float32(np.inf)
    for c in range(w):
        a0, a1, a2 = f(R[0, 0] * xn[c]), f(R[1, 0] * xn[c]), f(R[2, 0] * xn[c])
        best, best_r = 0, inf32
        for r in range(h):
            d = dep[r, c]
            oz = f(d * f(f(a2 + f(R[2, 1] * yn[r])) + R[2, 2]))
            z = f(oz + tz32)
            if valid[r, c] and z >= z0 and z <= z1:
                x = f(d * f(f(a0 + f(R[0, 1] * yn[r])) + R[0, 2]))
                y = f(d * f(f(a1 + f(R[1, 1] * yn[r])) + R[1, 2]))
                v = f(math.sqrt(f(f(x * x) + f(y * y))))
            else:
                v = inf32
            hit_rng[c, r] = v
            if v < best_r:
                best, best_r = r, v
        first_row[c], r1[c] = best, best_r
        best2, best2_r = 0, inf32
        for r in range(h):
            v = inf32 if r == best else hit_rng[c, r]
            if v < best2_r:
                best2, best2_r = r, v
        second_row[c], r2[c] = best2, best2_r


@numba.njit(cache=True, error_model="numpy")
def _column_rays(
    dep: NDArray[np.float32], valid: NDArray[np.bool_], xn: NDArray[np.float32], yn: NDArray[np.float32],
    R: NDArray[np.float32], c: int, tz32: np.float32, z0: np.float32, z1: np.float32, sensor_in_band: bool,
    ox: NDArray[np.float32], oy: NDArray[np.float32], zc: NDArray[np.float32], rng: NDArray[np.float32],
    s_lo: NDArray[np.float32], s_hi: NDArray[np.float32], crosses: NDArray[np.bool_],
) -> bool:
    """Fills, per pixel of column ``c``: offsets from the sensor, height, horizontal range, the
    ray's fractions [s_lo, s_hi] inside the band and whether a valid ray crosses it; returns
    whether any does."""
    f = _f32
    flat_eps = np.float32(1e-6)
    a0, a1, a2 = f(R[0, 0] * xn[c]), f(R[1, 0] * xn[c]), f(R[2, 0] * xn[c])
    any_cross = False
    for r in range(dep.shape[0]):
        d = dep[r, c]
        x = f(d * f(f(a0 + f(R[0, 1] * yn[r])) + R[0, 2]))
        y = f(d * f(f(a1 + f(R[1, 1] * yn[r])) + R[1, 2]))
        oz = f(d * f(f(a2 + f(R[2, 1] * yn[r])) + R[2, 2]))
        ox[r], oy[r], zc[r] = x, y, f(oz + tz32)
        rng[r] = f(math.sqrt(f(f(x * x) + f(y * y))))
        if abs(oz) < flat_eps:
            lo, hi = (0.0, 1.0) if sensor_in_band else (1.0, 0.0)
        else:
            sa = f(f(z0 - tz32) / oz)
            sb = f(f(z1 - tz32) / oz)
            lo = min(max(min(sa, sb), 0.0), 1.0)
            hi = min(max(max(sa, sb), 0.0), 1.0)
        s_lo[r], s_hi[r] = lo, hi
        crosses[r] = valid[r, c] and s_hi[r] > s_lo[r]
        any_cross = any_cross or crosses[r]
    return any_cross


@numba.njit(cache=True, error_model="numpy")
def _nearest_confirmed(
    r1: NDArray[np.float32], r2: NDArray[np.float32], c: int, rt: np.float32, rtp: np.float32, min_support: int,
) -> bool:
    """Whether column ``c``'s nearest in-band point counts: enough points back it up within
    the range tolerance (its next point or the neighbouring columns' nearest)."""
    f = _f32
    inf32 = np.float32(np.inf)
    q1 = r1[c]
    tol1 = f(rt + f(rtp * f(q1 * q1)))
    left = r1[c - 1] if c > 0 else inf32
    right = r1[c + 1] if c + 1 < r1.shape[0] else inf32
    support = 0
    for o in (r2[c], left, right):
        if abs(f(o - q1)) <= tol1:
            support += 1
    return support >= min_support


@numba.njit(cache=True, error_model="numpy")
def _cluster_mean_range(hit_rng: NDArray[np.float32], c: int, lower: np.float32, upper: np.float32) -> float:
    """Mean in-band range of column ``c`` over [lower, upper], the nearest cluster."""
    f = _f32
    acc = np.float32(0.0)
    n_in = 0
    for r in range(hit_rng.shape[1]):
        v = hit_rng[c, r]
        if v >= lower and v <= upper:
            acc = f(acc + v)
            n_in += 1
    # (numpy divided the float32 sum by an int64 count: float64 from here on.)
    return np.float64(acc) / max(n_in, 1)


@numba.njit(cache=True, error_model="numpy")
def _free_ends_and_hit_row(
    hit_rng: NDArray[np.float32], c: int, rng: NDArray[np.float32], s_lo: NDArray[np.float32],
    s_hi: NDArray[np.float32], crosses: NDArray[np.bool_], first_row_c: int, q1: np.float32, hit: bool,
    r_hit: float, tol: np.float32, free_sigma: float, sensor_in_band: bool,
) -> tuple[int, float, int, np.float32, int]:
    """Column ``c``'s free part as (row, ray fraction) where it ends and starts, and the row whose
    in-band range is closest to ``r_hit``: it ends at the nearest in-band point ``q1`` or, when
    farther, ``free_sigma`` noise sigmas short of the obstacle (with neither, where a ray leaves
    the band farthest), and starts where a ray enters the band nearest (inside it, at the sensor)."""
    f = _f32
    inf32 = np.float32(np.inf)
    exit_row, exit_v = 0, np.float32(-np.inf)
    near_row, near_v = 0, inf32
    med_row, med_v = 0, np.inf
    for r in range(rng.shape[0]):
        fr = f(s_hi[r] * rng[r]) if crosses[r] else np.float32(-1.0)
        if fr > exit_v:
            exit_row, exit_v = r, fr
        nr = f(s_lo[r] * rng[r]) if crosses[r] else inf32
        if nr < near_v:
            near_row, near_v = r, nr
        md = abs(np.float64(hit_rng[c, r]) - r_hit)
        if md < med_v:
            med_row, med_v = r, md
    blocked = math.isfinite(q1)
    far_row = first_row_c if blocked else exit_row
    r_first = rng[first_row_c]
    r_free = max(np.float64(q1), r_hit - f(f(free_sigma * tol) / 3.0)) if hit else np.float64(q1)
    far_s = r_free / r_first if blocked else np.float64(s_hi[far_row])
    if not math.isfinite(far_s):
        far_s = 0.0
    near_s = np.float32(0.0) if sensor_in_band else s_lo[near_row]
    return far_row, far_s, near_row, near_s, med_row
