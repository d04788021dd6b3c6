"""Geometry of one tracked detection: depth in its box -> an object observation in the map.

The pipeline per track (one I/O-free step, :func:`observe_object`):

1. The box, shrunk by ``box_shrink_frac`` on each side (box edges leak background), is
   back-projected through the pinhole model; large boxes are sampled with a pixel stride so at
   most ``max_box_points`` pixels are used. Invalid depth never becomes a point.
2. Points go to the map frame with the full rigid transform ``T_map_camera`` (which callers
   compose as ``T_map_body @ T_body_camera``, in SE(3)).
3. Points within ``floor_clearance_m`` of the floor plane are dropped: the floor is not part
   of any object, and it would join every leg into one cluster with the room.
   The wall behind the object goes too, with everything beyond it: a vertical plane fitted
   (:func:`background_walls`) on a ring of pixels just outside the box, accepted only when
   nothing of the ring or the box stands behind it and it faces the camera. A chair a few
   centimetres in front of a wall would otherwise be one cluster with the wall.
4. Voxel downsampling, then Euclidean clustering (:mod:`semmap.clustering`: exact single
   linkage) at a distance of ``cluster_distance_m`` or ``cluster_pixel_gaps`` sampled-pixel
   spacings at the box's far range, whichever is larger: a table top seen at a grazing angle
   has rows several spacings apart and must stay one cluster. The object is the nearest
   large cluster spanning the box (:func:`_pick_cluster`): a tight box is mostly its
   object, while a background far behind it can own more voxels than it does.
5. Hollow-bottom classes: RANSAC finds the seat / top plane, constrained near horizontal.
6. Footprint: the convex hull of the projection of the object's points (top and legs alike)
   onto the map plane, so the space between the legs is inside it. Heights are true heights
   above the floor plane; the position is the centroid of the object's (downsampled) points.

Also here: :class:`CameraView`, which tells whether a map point should be visible in a frame
(negative evidence for the object map). The polygon helpers are in :mod:`semmap.polygons`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.clustering import euclidean_clusters, voxel_downsample
from semmap.config import ClassConfig, GeometryConfig
from semmap.frames import Transform, invert
from semmap.pointcloud import valid_depth_mask, window_points_map
from semmap.polygons import convex_footprint, simplify_polygon
from semmap.ransac import Plane, fit_plane
from semmap.shape_prior import shape_mask
from semmap.types import CameraIntrinsics, Track

#: A box this close to the image border may be cut by it (detector boxes jitter by a few px).
_EDGE_MARGIN_PX = 8
#: Background walls are fitted on a ring of pixels around the box: this far outside it (box
#: jitter must not put the object's own edge in the ring), this wide, sampled at this stride.
_RING_GAP_PX = 4
_RING_WIDTH_PX = 12
_RING_STRIDE_PX = 4
#: A wall is a vertical plane holding at least this share of the ring's above-floor points
#: (and ``_WALL_MIN_POINTS``), with at most ``_WALL_MAX_BEHIND`` of them beyond it.
_WALL_MIN_SHARE = 0.15
_WALL_MIN_POINTS = 30
_WALL_MAX_BEHIND = 0.1
_WALL_HYPOTHESES = 64
#: A wall faces the camera: cosine between its normal and the line of sight at least this.
_WALL_MIN_FACING = 0.35
#: Rows of the per-point table in :func:`observe_object` after map x, y, z: height above
#: the floor, camera z-depth, floor clearance at that depth, pixel u, v.
_H, _RANGE, _CLEAR, _U = 3, 4, 5, 6


@dataclass(frozen=True, eq=False)
class ObjectObservation:
    """What one frame tells about one tracked object, in the map frame (metres).

    ``footprint_xy_m``: (M, 2) convex polygon, counter-clockwise, the object's projection on
    the map plane. ``z_min_m``/``z_max_m``: its height range above the floor. ``top_plane``:
    the horizontal seat/top plane found by RANSAC (hollow classes), ``top_height_m`` its height
    above the floor at the object's centroid. ``n_points`` counts the pixels of the object,
    ``n_voxels`` its downsampled points. ``range_m``: camera-to-centroid distance.
    ``at_image_edge``: the box touches the image border, so the view may be partial.
    ``points_xy_m``: the object's downsampled points projected on the map plane.
    """

    track_id: int
    class_name: str
    score: float
    stamp_s: float
    centroid_map_m: tuple[float, float, float]
    footprint_xy_m: NDArray[np.float64]  # (M, 2)
    z_min_m: float
    z_max_m: float
    n_points: int
    n_voxels: int
    range_m: float
    top_plane: Plane | None = None
    top_height_m: float | None = None
    at_image_edge: bool = False
    #: (K, 2) map-plane projection of the object's downsampled points (the footprint's
    #: evidence); empty when only the polygon is known.
    points_xy_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    #: The camera's map-plane position for this view (where the unseen side is); None unknown.
    camera_xy_m: tuple[float, float] | None = None
    #: (K, 3) the object's downsampled points in the map frame (which points are whose, when
    #: boxes of one frame overlap; see :mod:`semmap.frame_objects`).
    voxels_map_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def centroid_xy_m(self) -> NDArray[np.float64]:
        return np.asarray(self.centroid_map_m[:2], dtype=np.float64)

    @property
    def height_m(self) -> float:
        """The top of the object above the floor."""
        return self.z_max_m


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

    def expects_visible(self, points_map_m: NDArray[np.floating]) -> NDArray[np.bool_]:
        """(N,) True where a map point (N, 3) projects inside the image, within range, and the
        measured depth there (median of a 5x5 patch) is not nearer than the point by more than
        the tolerance. Pixels without valid depth are not evidence either way (False)."""
        pts = np.asarray(points_map_m, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(pts), dtype=bool)
        if len(pts) == 0:
            return out
        T = invert(np.asarray(self.T_map_camera, dtype=np.float64))
        pc = pts @ T[:3, :3].T + T[:3, 3]  # (N, 3) camera frame
        K = self.intrinsics
        z = pc[:, 2]
        in_range = (z >= self.depth_range_m[0]) & (z <= self.depth_range_m[1])
        zs = np.where(in_range, z, 1.0)
        u = K.fx_px * pc[:, 0] / zs + K.cx_px
        v = K.fy_px * pc[:, 1] / zs + K.cy_px
        m = self.margin_px
        inside = in_range & (u >= m) & (u < K.width_px - m) & (v >= m) & (v < K.height_px - m)
        d = np.asarray(self.depth_m)
        for i in np.nonzero(inside)[0]:
            ui, vi = int(u[i]), int(v[i])
            patch = d[max(0, vi - 2) : vi + 3, max(0, ui - 2) : ui + 3]
            ok = valid_depth_mask(patch, self.depth_range_m[0], self.depth_range_m[1])
            if ok.sum() == 0:
                continue
            measured = float(np.median(patch[ok]))
            out[i] = measured >= z[i] - self.tolerance_m
        return out


def voxel_keys(points_m: NDArray[np.floating], voxel_m: float, shift_m: float = 0.0) -> NDArray[np.int64]:
    """(N,) one integer per voxel ``floor((p + shift_m) / voxel_m)`` of points (N, 3) (21 bits
    per axis: +-31 km at 3 cm)."""
    ijk = _voxel_ijk(points_m, voxel_m, shift_m) + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def _voxel_ijk(points_m: NDArray[np.floating], voxel_m: float, shift_m: float = 0.0) -> NDArray[np.int64]:
    """(N, 3) voxel indices ``floor((p + shift_m) / voxel_m)`` of points (N, 3)."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    return np.floor((p + shift_m) / voxel_m).astype(np.int64)


#: Key differences of the 27 voxels around and including one (see :func:`voxel_keys`).
_NEIGHBOUR_KEY_STEPS = np.array([(i << 42) + (j << 21) + k for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                                dtype=np.int64)


#: Largest grid (cells) over the other points' bounds for :func:`within_a_voxel`'s lookup;
#: beyond it (points spread over a room) a binary search over keys costs less.
_DENSE_NEIGHBOUR_CELLS = 400_000


def within_a_voxel(a_m: NDArray[np.floating], b_m: NDArray[np.floating], voxel_m: float) -> NDArray[np.bool_]:
    """(N,) True where a point of ``a_m`` (N, 3) lies in a voxel of a point of ``b_m`` (M, 3) or
    in one of the 26 around it: exact, for taking other objects' points out of a box."""
    b_ijk = _voxel_ijk(b_m, voxel_m)
    a_ijk = _voxel_ijk(a_m, voxel_m)
    if len(b_ijk) == 0:
        return np.zeros(len(a_ijk), dtype=bool)
    lo, hi = b_ijk.min(axis=0) - 1, b_ijk.max(axis=0) + 1
    shape = hi - lo + 1
    if float(np.prod(shape.astype(np.float64))) > _DENSE_NEIGHBOUR_CELLS:
        # A binary search of each neighbour key among b's sorted keys (np.isin would hash all
        # 27 x M grown keys on every call, ten times slower at a frame's sizes).
        wanted = voxel_keys(a_m, voxel_m)[:, None] - _NEIGHBOUR_KEY_STEPS[None, :]  # (N, 27)
        return np.asarray(_in_sorted(wanted, np.sort(voxel_keys(b_m, voxel_m))).any(axis=1), dtype=bool)
    # b's voxels and their 26 neighbours on a small grid over b's bounds, looked up per point.
    grid = np.zeros(tuple(shape.tolist()), dtype=bool)
    rel = b_ijk - lo
    grid[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    for axis in range(3):
        src = grid.copy()
        lower = [slice(None)] * 3
        upper = [slice(None)] * 3
        lower[axis], upper[axis] = slice(None, -1), slice(1, None)
        grid[tuple(upper)] |= src[tuple(lower)]
        grid[tuple(lower)] |= src[tuple(upper)]
    out = np.zeros(len(a_ijk), dtype=bool)
    inside = np.flatnonzero(np.all((a_ijk >= lo) & (a_ijk <= hi), axis=1))
    rel = a_ijk[inside] - lo
    out[inside] = grid[rel[:, 0], rel[:, 1], rel[:, 2]]
    return out


def _in_sorted(keys: NDArray[np.int64], sorted_keys: NDArray[np.int64]) -> NDArray[np.bool_]:
    """True where an element of ``keys`` (any shape) is in ``sorted_keys`` (K,), ascending."""
    if len(sorted_keys) == 0:
        return np.zeros(keys.shape, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return np.asarray(sorted_keys[at] == keys, dtype=bool)


def shrink_box(
    xyxy_px: tuple[float, float, float, float], frac: float, width_px: int, height_px: int
) -> tuple[int, int, int, int]:
    """Integer half-open pixel window (u0, v0, u1, v1) of a box shrunk by ``frac`` of its width
    and height on each side, clipped to the image."""
    u0, v0, u1, v1 = xyxy_px
    du, dv = (u1 - u0) * frac, (v1 - v0) * frac
    a = max(0, int(math.floor(u0 + du)))
    b = max(0, int(math.floor(v0 + dv)))
    c = min(width_px, int(math.ceil(u1 - du)))
    d = min(height_px, int(math.ceil(v1 - dv)))
    return a, b, c, d


def _pick_cluster(
    labels: NDArray[np.int64], range_m: NDArray[np.float64], uv: NDArray[np.int64],
    window: tuple[int, int, int, int], min_frac: float, min_cover: float,
) -> int:
    """The object's cluster (``labels`` (N,) ordered by size, ``uv`` (N, 2) pixels).

    Candidates hold at least ``min_frac`` of the largest cluster's pixels. A tight box is
    spanned by its object, so candidates whose pixel extent covers less of the box than
    ``min_cover`` times the best coverage are dropped (an occluder in front spans part of the
    box); of the rest, the one nearest the camera wins (the wall behind also spans the box,
    but farther away).
    """
    counts = np.bincount(labels)
    candidates = np.nonzero(counts >= min_frac * counts.max())[0]
    if len(candidates) == 1:
        return int(candidates[0])
    u0, v0, u1, v1 = window
    area = float(max(1, (u1 - u0) * (v1 - v0)))
    # Per-cluster pixel extents in one pass: sort by label, reduce each run.
    order = np.argsort(labels, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[candidates]
    su, sv = uv[order, 0], uv[order, 1]
    ext_u = np.maximum.reduceat(su, starts) - np.minimum.reduceat(su, starts) + 1
    ext_v = np.maximum.reduceat(sv, starts) - np.minimum.reduceat(sv, starts) + 1
    if len(candidates) > 0:
        # reduceat runs each slice to the next start; the last candidate's run must stop at
        # its own end, so recompute the candidates whose run is not followed by theirs.
        ends = starts + counts[candidates]
        for i in range(len(candidates)):
            nxt = starts[i + 1] if i + 1 < len(candidates) else len(order)
            if nxt != ends[i]:
                seg = slice(starts[i], ends[i])
                ext_u[i] = su[seg].max() - su[seg].min() + 1
                ext_v[i] = sv[seg].max() - sv[seg].min() + 1
    cover = ext_u * ext_v / area
    sr = range_m[order]
    med = np.array([float(np.median(sr[a : a + counts[c]])) for a, c in zip(starts, candidates, strict=True)])
    med[cover < min_cover * cover.max()] = np.inf
    return int(candidates[int(np.argmin(med))])


def _median(values: NDArray[np.float64]) -> float:
    """``np.median`` of (N,) finite values (N >= 1), the same number, by one partition
    without its NaN checks and dispatch (a few times cheaper on the few hundred values here)."""
    n = len(values)
    k = n // 2
    if n % 2:
        return float(np.partition(values, k)[k])
    part = np.partition(values, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2.0)


def _quantile_lower(values: NDArray[np.float64], q: float) -> float:
    """The ``q`` quantile of (N,) values by selection (the sample at or below it, no
    interpolation): O(N), without a full sort."""
    k = int(q * (len(values) - 1))
    return float(np.partition(values, k)[k])


def _ring_windows(
    xyxy_px: tuple[float, float, float, float], width_px: int, height_px: int,
) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """The ring of pixels just outside a box, for finding the wall behind the object: its
    outer window (u0, v0, u1, v1), clipped to the image, and the hole in it (the box grown by
    the gap), both half-open, the hole on the ring's sample grid (``_RING_STRIDE_PX``)."""
    u0, v0, u1, v1 = xyxy_px
    g, w, s = _RING_GAP_PX, _RING_GAP_PX + _RING_WIDTH_PX, _RING_STRIDE_PX
    ou0, ov0 = max(0, int(u0) - w), max(0, int(v0) - w)
    ou1, ov1 = min(width_px, int(math.ceil(u1)) + w), min(height_px, int(math.ceil(v1)) + w)
    # First and last-but-one sample index inside the grown box, per axis.
    r0, r1 = -(-(int(v0) - g - ov0) // s), -(-(int(math.ceil(v1)) + g - ov0) // s)
    c0, c1 = -(-(int(u0) - g - ou0) // s), -(-(int(math.ceil(u1)) + g - ou0) // s)
    hole = (ou0 + s * max(0, c0), ov0 + s * max(0, r0), ou0 + s * max(0, c1), ov0 + s * max(0, r1))
    return (ou0, ov0, ou1, ov1), hole


def _noise_tolerance_m(range_m: NDArray[np.float64], params: GeometryConfig) -> NDArray[np.float64]:
    """(N,) distance within which a point at ``range_m`` (N,) counts as on a surface: the RANSAC
    distance plus half the floor cut's range-squared term (depth noise grows with range^2)."""
    return params.ransac_distance_m + 0.5 * params.floor_clearance_per_m2 * range_m**2


@numba.njit(cache=True)
def _fit_wall(
    xy: NDArray[np.float64], tol: NDArray[np.float64], remaining: NDArray[np.bool_], pairs: NDArray[np.int64],
    min_support: float, cam_x: float, cam_y: float, max_behind: float, min_facing: float,
    out_inliers: NDArray[np.bool_],
) -> tuple[bool, float, float, float]:
    """One wall search of :func:`background_walls`, compiled (numba, cached as in
    :mod:`semmap.clustering`): ``(found, normal x, normal y, offset)``, the wall's points
    written to ``out_inliers`` (N,).

    ``xy`` (N, 2) above-floor ring points with tolerances ``tol`` (N,); ``pairs`` (Hy, 2) the
    drawn point pairs, each a line hypothesis (pairs closer than 5 cm are none). The line with
    most ``remaining`` points within their tolerance wins (first of equals) and is refitted by
    least squares (the major axis of its points' 2x2 scatter), its normal turned towards the
    camera. It is a wall with at least ``min_support`` remaining points on it, at most
    ``max_behind`` of all points beyond it, and seen at least ``min_facing`` (cosine) face-on.
    """
    n_all = xy.shape[0]
    best, best_support = -1, -1
    best_nx, best_ny, best_off = 0.0, 0.0, 0.0
    for hyp in range(pairs.shape[0]):
        i, j = pairs[hyp, 0], pairs[hyp, 1]
        dx, dy = xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]
        length = math.hypot(dx, dy)
        if length <= 0.05:
            continue
        nx, ny = -dy / length, dx / length
        off = -(nx * xy[i, 0] + ny * xy[i, 1])
        support = 0
        for k in range(n_all):
            if remaining[k] and abs(xy[k, 0] * nx + xy[k, 1] * ny + off) <= tol[k]:
                support += 1
        if support > best_support:
            best, best_support = hyp, support
            best_nx, best_ny, best_off = nx, ny, off
    if best < 0 or best_support < min_support:
        return False, 0.0, 0.0, 0.0
    # Least squares on the winner's points: centroid, then the scatter's major axis.
    sx, sy, m = 0.0, 0.0, 0
    for k in range(n_all):
        if remaining[k] and abs(xy[k, 0] * best_nx + xy[k, 1] * best_ny + best_off) <= tol[k]:
            sx += xy[k, 0]
            sy += xy[k, 1]
            m += 1
    cx, cy = sx / m, sy / m
    sxx, sxy, syy = 0.0, 0.0, 0.0
    for k in range(n_all):
        if remaining[k] and abs(xy[k, 0] * best_nx + xy[k, 1] * best_ny + best_off) <= tol[k]:
            ex, ey = xy[k, 0] - cx, xy[k, 1] - cy
            sxx += ex * ex
            sxy += ex * ey
            syy += ey * ey
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    nx, ny = -math.sin(theta), math.cos(theta)
    off = -(nx * cx + ny * cy)
    if nx * cam_x + ny * cam_y + off < 0:
        nx, ny, off = -nx, -ny, -off
    n_in, n_behind = 0, 0
    for k in range(n_all):
        dist = xy[k, 0] * nx + xy[k, 1] * ny + off
        out_inliers[k] = remaining[k] and abs(dist) <= tol[k]
        if out_inliers[k]:
            n_in += 1
        if dist < -tol[k]:
            n_behind += 1
    if n_in < min_support:
        return False, 0.0, 0.0, 0.0
    if n_behind / n_all > max_behind:
        return False, 0.0, 0.0, 0.0  # things stand behind it: a piece of furniture, not the room's boundary
    vx, vy = cx - cam_x, cy - cam_y
    if abs(nx * vx + ny * vy) < min_facing * math.hypot(vx, vy):
        return False, 0.0, 0.0, 0.0  # seen edge-on: a strip of something along the line of sight
    return True, nx, ny, off


def background_walls(
    ring_xy_m: NDArray[np.float64], ring_range_m: NDArray[np.float64], camera_xy_m: NDArray[np.float64],
    params: GeometryConfig, rng: np.random.Generator,
) -> list[tuple[NDArray[np.float64], float]]:
    """Vertical planes (walls) behind an object, from the points around its box.

    ``ring_xy_m``: (N, 2) map-plane positions of the pixels around the box that lie above
    the floor cut, ``ring_range_m`` (N,) their camera z-depths, ``camera_xy_m`` (2,). A wall
    is a vertical plane (a line in the map plane) holding a large share of those points with
    almost none beyond it: the room's boundary, which nothing stands behind. Returns up to
    two walls (a corner) as ``(normal_xy (2,), offset_m)`` with the normal towards the
    camera, so ``normal . xy + offset`` is the distance in front of the wall.
    """
    xy = np.ascontiguousarray(ring_xy_m, dtype=np.float64).reshape(-1, 2)
    n_all = len(xy)
    if n_all < _WALL_MIN_POINTS:
        return []
    tol = _noise_tolerance_m(np.asarray(ring_range_m, dtype=np.float64), params)  # (N,)
    remaining = np.ones(n_all, dtype=bool)
    walls: list[tuple[NDArray[np.float64], float]] = []
    cam_x, cam_y = float(camera_xy_m[0]), float(camera_xy_m[1])
    for share in (_WALL_MIN_SHARE, _WALL_MIN_SHARE / 2):
        idx = np.nonzero(remaining)[0]
        if len(idx) < _WALL_MIN_POINTS:
            break
        pairs = idx[rng.integers(0, len(idx), size=(_WALL_HYPOTHESES, 2))]
        inl = np.empty(n_all, dtype=bool)
        found, nx, ny, off = _fit_wall(xy, tol, remaining, pairs, float(max(_WALL_MIN_POINTS, share * n_all)),
                                       cam_x, cam_y, _WALL_MAX_BEHIND, _WALL_MIN_FACING, inl)
        if not found:
            break
        walls.append((np.array([nx, ny]), off))
        remaining &= ~inl
    return walls


def observe_object(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    T_map_camera: Transform,
    track: Track,
    class_cfg: ClassConfig,
    params: GeometryConfig,
    floor: Plane | None = None,
    depth_range_m: tuple[float, float] = (0.0, math.inf),
    stamp_s: float = 0.0,
    rng: np.random.Generator | None = None,
    *,
    cluster_by: Literal["box", "voxels"] = "box",
    remove_walls: bool = True,
    exclude_voxels_m: NDArray[np.float64] | None = None,
    same_object_as_m: NDArray[np.float64] | None = None,
    shape_prior: bool = True,
) -> ObjectObservation | None:
    """The object a track's box shows, or None when its depth holds no object.

    ``depth_m``: (H, W) metres, 0/NaN invalid; pixels outside ``depth_range_m`` are invalid
    too. ``T_map_camera``: (4, 4) optical camera -> map. ``floor``: the floor plane in the map
    frame with its normal up (default: z = 0, the map plane). ``class_cfg.hollow`` decides
    whether a top plane is searched. Returns None when fewer than ``min_cluster_points``
    voxels survive (an empty, distant or all-floor box). ``cluster_by``: "box" picks the
    nearest large cluster spanning the box (see :func:`_pick_cluster`); "voxels" the cluster
    with most voxels (Open3D's usual choice after ``cluster_dbscan``, for comparisons).
    ``remove_walls``: drop the wall behind the object first (:func:`background_walls`, fitted
    on the pixels around the box) with everything beyond it. ``exclude_voxels_m`` (K, 3):
    points of other objects (voxel centres, map frame); the box's points in their voxels
    are not this object's. ``same_object_as_m`` (K, 3): the object is the cluster holding most
    of these points (a second look at the same object, see :mod:`semmap.frame_objects`).
    ``shape_prior``: apply the class's shape prior (:mod:`semmap.shape_prior`).
    """
    floor = floor if floor is not None else Plane.horizontal()
    H, W = np.asarray(depth_m).shape
    window = shrink_box(track.xyxy_px, params.box_shrink_frac, W, H)
    u0, v0, u1, v1 = window
    area = max(0, u1 - u0) * max(0, v1 - v0)
    if area == 0:
        return None
    stride = max(1, int(math.ceil(math.sqrt(area / params.max_box_points))))
    # One (8, N) table - map x, y, z, height above the floor, z-depth, floor clearance,
    # pixel u, v; one row each - of the box's points above the floor cut, so each filter
    # below is a single gather instead of one per quantity.
    t = T_map_camera[:3, 3]
    tab, n_all = window_points_map(
        depth_m, intrinsics, depth_range_m[0], depth_range_m[1], window, stride, T_map_camera,
        floor.normal_array, floor.offset_m, params.floor_clearance_m, params.floor_clearance_per_m2,
    )
    if n_all < params.min_cluster_points or tab.shape[1] < params.min_cluster_points:
        return None
    # A wall behind the object (found around the box) goes, with everything beyond it: an
    # object a few cm in front of a wall would otherwise cluster together with it.
    rng = rng if rng is not None else np.random.default_rng(0)
    n_ring = 0
    if remove_walls:
        # The ring's valid pixels (n_ring) and, as a table like the box's, those above the
        # floor cut: what the wall is fitted on.
        outer, hole = _ring_windows(track.xyxy_px, W, H)
        ring_tab, n_ring = window_points_map(
            depth_m, intrinsics, depth_range_m[0], depth_range_m[1], outer, _RING_STRIDE_PX, T_map_camera,
            floor.normal_array, floor.offset_m, params.floor_clearance_m, params.floor_clearance_per_m2,
            hole_px=hole,
        )
    if n_ring >= _WALL_MIN_POINTS:
        walls = background_walls(ring_tab[:2].T, ring_tab[_RANGE], t[:2], params, rng)
        if walls:
            tol = _noise_tolerance_m(tab[_RANGE], params)
            front = np.ones(tab.shape[1], dtype=bool)
            for n_xy, off in walls:
                dist = n_xy @ tab[:2] + off  # (N,) in front of the wall
                # Nothing of the box stands behind a wall; a "wall" with the box's points
                # behind it is an occluder in front of the object.
                if np.count_nonzero(dist < -tol) <= _WALL_MAX_BEHIND * len(dist):
                    front &= dist > tol
            if not front.all():
                if np.count_nonzero(front) < params.min_cluster_points:
                    return None  # the box shows the wall only
                tab = tab[:, front]
    if exclude_voxels_m is not None and len(exclude_voxels_m):
        mine = ~within_a_voxel(tab[:3].T, exclude_voxels_m, params.voxel_size_m)
        if np.count_nonzero(mine) < params.min_cluster_points:
            return None  # the box shows other objects only
        tab = tab[:, mine]
    pts = tab[:3].T  # (N, 3) view
    heights, rng_cam, clearance = tab[_H], tab[_RANGE], tab[_CLEAR]

    vox, inverse = voxel_downsample(pts, params.voxel_size_m)  # (M, 3), (N,)
    spacing_m = stride * _quantile_lower(rng_cam, 0.9) / min(intrinsics.fx_px, intrinsics.fy_px)
    eps = max(params.cluster_distance_m, params.cluster_pixel_gaps * spacing_m)
    vox_label = euclidean_clusters(vox, eps)
    point_label = vox_label[inverse]
    if cluster_by == "voxels":
        best = 0  # labels are ordered by voxel count
    elif same_object_as_m is not None and len(same_object_as_m):
        # The object seen before (this box's first look, less other objects' points): the
        # cluster holding most of it, not whatever now spans the box best.
        ours = _in_sorted(voxel_keys(vox, params.voxel_size_m),
                          np.sort(voxel_keys(same_object_as_m, params.voxel_size_m)))
        best = int(np.argmax(np.bincount(vox_label[ours], minlength=int(vox_label.max()) + 1))) if ours.any() else 0
    else:
        best = _pick_cluster(point_label, rng_cam, tab[_U:].T.astype(np.int64), window,
                             params.cluster_min_pixel_frac, params.cluster_min_box_cover)
    obj_idx = np.flatnonzero(vox_label == best)
    if shape_prior and class_cfg.shape != "free":
        # Touching furniture is one cluster: the class's shape says which part is this object.
        obj_vox = vox[obj_idx]
        keep = shape_mask(obj_vox, floor.signed_distance_m(obj_vox), class_cfg.shape, params.voxel_size_m,
                          params.min_plane_points)
        if keep.sum() < params.min_cluster_points:
            return None  # the box shows another object's top only
        if not keep.all():
            piece = euclidean_clusters(obj_vox[keep], eps)  # what is left may fall apart
            obj_idx = obj_idx[keep][piece == 0]
    obj_vox = vox[obj_idx]
    if len(obj_vox) < params.min_cluster_points:
        return None
    in_obj = np.zeros(len(vox), dtype=bool)
    in_obj[obj_idx] = True
    on_obj = np.flatnonzero(in_obj[inverse])
    obj_h = heights[on_obj]
    # Clearance at the object's lowest point: the floor cut removed up to that much of it.
    lowest = int(np.argmin(obj_h))
    lowest_clearance = float(clearance[on_obj[lowest]])

    z_max = _quantile_lower(obj_h, params.height_quantile)
    z_min = float(obj_h[lowest])
    # Standing on the floor: its lowest points were cut with the floor, so it reaches z = 0.
    if z_min <= lowest_clearance + params.voxel_size_m:
        z_min = 0.0
    centroid = obj_vox.mean(axis=0)

    top_plane: Plane | None = None
    top_height: float | None = None
    if class_cfg.hollow != "none":
        fit = fit_plane(
            obj_vox, params.ransac_distance_m, params.ransac_iterations, rng,
            up=floor.normal_array, max_tilt_rad=math.radians(params.plane_max_tilt_deg),
            min_inliers=params.min_plane_points,
        )
        if fit is not None:
            top_plane = fit.plane
            inl = obj_vox[fit.inliers]
            top_height = _median(floor.signed_distance_m(inl))
    if shape_prior and class_cfg.shape == "table" and top_height is not None:
        z_min = 0.0  # a table stands on the floor on legs the chairs round it often hide

    # Projection onto the map plane: all object points, the top among them, so the space
    # between legs lies inside the hull.
    footprint = simplify_polygon(convex_footprint(obj_vox[:, :2], min_width_m=params.voxel_size_m),
                                 params.voxel_size_m / 2)
    cam_pos = T_map_camera[:3, 3]
    bu0, bv0, bu1, bv1 = track.xyxy_px
    m = _EDGE_MARGIN_PX
    touches = bu0 <= m or bv0 <= m or bu1 >= W - m or bv1 >= H - m
    return ObjectObservation(
        track_id=track.track_id,
        class_name=track.class_name,
        score=float(track.score),
        stamp_s=float(stamp_s),
        centroid_map_m=(float(centroid[0]), float(centroid[1]), float(centroid[2])),
        footprint_xy_m=footprint,
        points_xy_m=obj_vox[:, :2].copy(),
        z_min_m=z_min,
        z_max_m=z_max,
        n_points=len(on_obj),
        n_voxels=len(obj_vox),
        range_m=float(np.linalg.norm(centroid - cam_pos)),
        top_plane=top_plane,
        top_height_m=top_height,
        at_image_edge=bool(touches),
        camera_xy_m=(float(cam_pos[0]), float(cam_pos[1])),
        voxels_map_m=obj_vox,
    )
