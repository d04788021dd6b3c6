"""A depth image turned into a 2D scan of one height band (the grid's input).

For each image column the scan keeps the nearest obstacle point whose height lies inside the
band (a virtual 2D lidar at flight altitude, as the reference design derives Cartographer's
scan from the point cloud). Free space is what valid rays crossed *inside the band*: from
where a ray enters the band to where it leaves it, ends, or meets the column's nearest
in-band obstacle. Rays with invalid depth (0, NaN, out of range) say nothing: a RealSense
returns 0 for "no echo", which must not clear the map.

Everything is vectorised over the (subsampled) image: the map-frame direction of every pixel
is ``R @ [(u - cx)/fx, (v - cy)/fy, 1]``, so a point is ``t + depth * direction`` without
building an (N, 3) cloud first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import VerticalBand
from semmap.errors import FrameError
from semmap.pointcloud import valid_depth_mask
from semmap.types import CameraIntrinsics


@dataclass(frozen=True, eq=False)
class BandScan:
    """One fan of rays in the map frame, one ray per used image column, ordered by column.

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
    nearest point alone is biased towards the sensor. Free space ends ``free_sigma`` noise
    sigmas (``tol / 3``) before the obstacle, or at the nearest point if that is farther.
    """
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
    s = max(1, int(stride_px))
    sc = max(1, int(column_stride_px)) if column_stride_px is not None else s
    sub = d[::s, ::sc].astype(np.float32, copy=False)  # (h, w)
    valid = valid_depth_mask(sub, min_depth_m, max_depth_m)
    if recover_px:
        sub, valid = recover_skipped(d, sub, valid, s, sc, min_depth_m, max_depth_m)
    dep = np.where(valid, sub, np.float32(0.0))
    if fill_px > 0:
        dep, valid = fill_dropouts(dep, valid, max(1, int(round(fill_px / s))))
    us = np.arange(0, W, sc, dtype=np.float32)
    vs = np.arange(0, H, s, dtype=np.float32)
    xn = (us - np.float32(intrinsics.cx_px)) / np.float32(intrinsics.fx_px)  # (w,)
    yn = (vs - np.float32(intrinsics.cy_px)) / np.float32(intrinsics.fy_px)  # (h,)
    R = T[:3, :3].astype(np.float32)
    tx, ty, tz = (float(v) for v in T[:3, 3])

    # Map-frame offset of each pixel's point from the sensor: depth * R @ [xn, yn, 1].
    ox = dep * (R[0, 0] * xn[None, :] + R[0, 1] * yn[:, None] + R[0, 2])
    oy = dep * (R[1, 0] * xn[None, :] + R[1, 1] * yn[:, None] + R[1, 2])
    oz = dep * (R[2, 0] * xn[None, :] + R[2, 1] * yn[:, None] + R[2, 2])
    z = oz + np.float32(tz)
    # Horizontal range of each point, (h, w). sqrt(x^2 + y^2) in float32 is within one ulp
    # of np.hypot (0.5 um at 5 m) at a sixth of its cost (hypot has no vectorised loop).
    rng = ox * ox
    rng += oy * oy
    np.sqrt(rng, out=rng)

    # The part of each ray s in [0, 1] (sensor -> point) inside the band, as [s_lo, s_hi].
    z0, z1 = np.float32(band.z_min_m), np.float32(band.z_max_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        sa = (z0 - np.float32(tz)) / oz
        sb = (z1 - np.float32(tz)) / oz
    flat = np.abs(oz) < 1e-6
    sensor_in_band = bool(band.z_min_m <= tz <= band.z_max_m)
    s_lo = np.where(flat, 0.0 if sensor_in_band else 1.0, np.clip(np.minimum(sa, sb), 0.0, 1.0))
    s_hi = np.where(flat, 1.0 if sensor_in_band else 0.0, np.clip(np.maximum(sa, sb), 0.0, 1.0))
    crosses = valid & (s_hi > s_lo)
    in_band = valid & (z >= z0) & (z <= z1)

    cols = np.arange(dep.shape[1])
    hit_rng = np.where(in_band, rng, np.float32(np.inf))
    # The nearest and second-nearest in-band point of each column (no full sort needed).
    first_row = np.argmin(hit_rng, axis=0)  # (w,)
    r1 = hit_rng[first_row, cols]
    rest = hit_rng.copy()
    rest[first_row, cols] = np.inf
    second_row = np.argmin(rest, axis=0)
    r2 = rest[second_row, cols]
    # A column's nearest in-band point counts if enough points back it up within the range
    # tolerance: the column's next point or the neighbouring columns' nearest. A thin table
    # edge spans columns; a flying pixel is alone.
    with np.errstate(invalid="ignore"):
        tol1 = np.float32(range_tolerance_m) + np.float32(range_tolerance_per_m2) * r1**2
        left = np.concatenate([[np.inf], r1[:-1]]).astype(np.float32)
        right = np.concatenate([r1[1:], [np.inf]]).astype(np.float32)
        support = sum((np.abs(o - r1) <= tol1).astype(np.int32) for o in (r2, left, right))
    confirmed = support >= max(0, int(min_hit_points) - 1)
    r_near = np.where(confirmed, r1, r2)
    is_hit = np.isfinite(r_near)
    hit_row = np.where(confirmed, first_row, second_row)
    # The nearest minimum of noisy ranges is biased towards the sensor (by ~2 sigma for a
    # wall seen by 50 pixels), so the obstacle is placed at the mean of the nearest cluster,
    # [r_near, r_near + cluster_tol * tol] (1 tol measured best on simulated rooms: wider
    # windows reach through thin parts to what lies behind them).
    r_near_f = np.where(is_hit, r_near, np.float32(0.0))
    tol = np.float32(range_tolerance_m) + np.float32(range_tolerance_per_m2) * r_near_f**2
    in_cluster = (hit_rng >= r_near_f[None, :]) & (hit_rng <= (r_near_f + cluster_tol * tol)[None, :])
    n_in = np.maximum(in_cluster.sum(axis=0), 1)
    r_hit = np.where(is_hit, np.where(in_cluster, hit_rng, 0.0).sum(axis=0) / n_in, np.float32(0.0))

    # Far end of the free part: near the obstacle, or the nearest in-band point when there is
    # no confirmed obstacle (an unconfirmed point still blocks), else the farthest band exit
    # of the column's rays.
    blocked = np.isfinite(r1)
    far_rng = np.where(crosses, s_hi * rng, np.float32(-1.0))
    exit_row = np.argmax(far_rng, axis=0)
    far_row = np.where(blocked, first_row, exit_row)
    # The cluster pixel nearest the mean range gives the obstacle's bearing (columns of a
    # tilted camera are not vertical planes).
    med_row = np.argmin(np.abs(hit_rng - r_hit[None, :]), axis=0)
    # Free space reaches to one noise sigma (tol / 3) before the obstacle, not just to the
    # nearest (most negatively noisy) point, so cells in front of a surface that a noisy
    # hit once marked get cleared again by later scans.
    r_first = rng[first_row, cols]
    r_free = np.where(is_hit, np.maximum(r1, r_hit - free_sigma * tol / 3.0), r1)
    with np.errstate(divide="ignore", invalid="ignore"):
        far_s = np.where(blocked, r_free / r_first, s_hi[far_row, cols])
    far_s = np.nan_to_num(far_s, nan=0.0, posinf=0.0)
    near_rng = np.where(crosses, s_lo * rng, np.float32(np.inf))
    near_row = np.argmin(near_rng, axis=0)
    near_s = s_lo[near_row, cols]
    if sensor_in_band:
        near_s = np.zeros_like(near_s)

    ray_valid = np.any(crosses, axis=0) | blocked
    origin = np.array([tx, ty])
    dxy_far = np.stack([ox[far_row, cols], oy[far_row, cols]], axis=1).astype(np.float64)
    far = origin + dxy_far * far_s[:, None]
    # That pixel's bearing at the cluster's mean range (the more precise estimate).
    dxy_med = np.stack([ox[med_row, cols], oy[med_row, cols]], axis=1).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(is_hit, r_hit / rng[med_row, cols], 1.0)
    hit_xy = origin + dxy_med * np.nan_to_num(scale, nan=1.0, posinf=1.0)[:, None]
    near = origin + np.stack([ox[near_row, cols], oy[near_row, cols]], axis=1) * near_s[:, None]
    hit_z = np.where(is_hit, z[hit_row, cols], np.nan)
    return BandScan(
        stamp_s=stamp_s, band=band, origin_xy_m=origin,
        near_xy_m=near.astype(np.float64), far_xy_m=far.astype(np.float64),
        hit_xy_m=hit_xy.astype(np.float64), is_hit=is_hit & ray_valid, valid=ray_valid, hit_z_m=hit_z.astype(np.float64),
    )
