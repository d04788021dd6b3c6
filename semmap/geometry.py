"""Geometry of one tracked detection: depth in its box -> an object observation in the map.

The pipeline per track (one I/O-free step, :func:`observe_object`): the box's points
(:func:`semmap.box_points.box_points`, steps 1-3 there), then the object among them
(:func:`object_in_box`, 4-6).

4. Voxel downsampling, then Euclidean clustering (:mod:`semmap.clustering`: exact single
   linkage) at a distance of ``cluster_distance_m`` or ``cluster_pixel_gaps`` sampled-pixel
   spacings at the box's far range, whichever is larger: a table top seen at a grazing angle
   has rows several spacings apart and must stay one cluster. The object is the nearest
   large cluster spanning the box (:func:`_pick_cluster`): a tight box is mostly its
   object, while a background far behind it can own more voxels than it does. A table's is
   a farther candidate when the nearest shows no top of the class and the farther one a much
   wider one (:func:`_widest_top`): chairs pulled up in front of a table span its box too.
5. Hollow-bottom classes: RANSAC finds the seat / top plane, constrained near horizontal.
6. Footprint: the convex hull of the projection of the object's points (top and legs alike)
   onto the map plane, so the space between the legs is inside it. Heights are true heights
   above the floor plane; the position is the centroid of the object's (downsampled) points.

The polygon helpers are in :mod:`semmap.polygons`; what a frame could see (negative
evidence, edges the image border cut) is in :mod:`semmap.camera_view`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from semmap.box_points import BoxPoints, box_points
from semmap.clustering import euclidean_clusters, voxel_downsample
from semmap.config import ClassConfig, GeometryConfig
from semmap.frames import Transform
from semmap.noise_bridges import dense_parts
from semmap.pointcloud import (
    CLEARANCE_ROW,
    HEIGHT_ROW,
    PIXEL_U_ROW,
    RANGE_ROW,
)
from semmap.polygons import convex_footprint, simplify_polygon
from semmap.ransac import Plane, fit_plane
from semmap.shape_prior import horizontal_layers, shape_mask
from semmap.types import CameraIntrinsics, Track
from semmap.voxels import in_sorted, voxel_keys, within_a_voxel

#: A box this close to the image border may be cut by it (detector boxes jitter by a few px).
_EDGE_MARGIN_PX = 8
#: A table's farther candidate cluster wins when its top spans this many times the nearest's.
TOP_WINS_FACTOR = 2.0
#: ... and when its top's height fits the class's prior within this (metres).
TOP_HEIGHT_TOLERANCE_M = 0.05
#: Candidates whose tops are measured (the nearest first): each costs a layer search.
_MAX_TOP_CANDIDATES = 3


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
    #: (M,) per footprint edge (vertex k to k+1): the depth image's border drew it, not the
    #: object (:func:`semmap.camera_view.cut_edges`); None when not known.
    footprint_edge_cut: NDArray[np.bool_] | None = None

    @property
    def centroid_xy_m(self) -> NDArray[np.float64]:
        return np.asarray(self.centroid_map_m[:2], dtype=np.float64)

    @property
    def height_m(self) -> float:
        """The top of the object above the floor."""
        return self.z_max_m


def _pick_cluster(
    labels: NDArray[np.int64], range_m: NDArray[np.float64], uv: NDArray[np.int64],
    window: tuple[int, int, int, int], min_frac: float, min_cover: float,
) -> list[int]:
    """The clusters that may be the object (``labels`` (N,) ordered by size, ``uv`` (N, 2)
    pixels), the likeliest first.

    Candidates hold at least ``min_frac`` of the largest cluster's pixels. A tight box is
    spanned by its object, so candidates whose pixel extent covers less of the box than
    ``min_cover`` times the best coverage are dropped (an occluder in front spans part of the
    box); the rest are ordered nearest the camera first (the wall behind also spans the box,
    but farther away).
    """
    counts = np.bincount(labels)
    candidates = np.nonzero(counts >= min_frac * counts.max())[0]
    if len(candidates) == 1:
        return [int(candidates[0])]
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
    order_near = np.argsort(med, kind="stable")
    return [int(candidates[k]) for k in order_near if np.isfinite(med[k])]


def _widest_top(vox: NDArray[np.float64], vox_label: NDArray[np.int64], heights_m: NDArray[np.float64],
                candidates: list[int], class_cfg: ClassConfig, params: GeometryConfig) -> int:
    """Of a table's candidate clusters (nearest first), the nearest, unless its top (its highest
    large horizontal surface, :func:`semmap.shape_prior.horizontal_layers`) is not a top of the
    class (``prior``: outside its height range, give or take ``TOP_HEIGHT_TOLERANCE_M``, or
    narrower than its least width) and a farther one's top of the class spans more than
    ``TOP_WINS_FACTOR`` times its area. Chairs in front of a table are nearer and as large,
    but their highest surface is a row of backrests; a counter behind a coffee table is not
    the coffee table, nor is a second desk behind a desk."""
    prior = class_cfg.prior
    heights_ok = prior.height_m if prior is not None else None
    least_width_m = prior.footprint_short_m[0] if prior is not None and prior.footprint_short_m else 0.0
    areas = []
    for k, c in enumerate(candidates[:_MAX_TOP_CANDIDATES]):
        members = vox_label == c
        tops = horizontal_layers(vox[members], heights_m[members], params.voxel_size_m, params.min_plane_points,
                                 highest_only=True)
        at_height = bool(tops) and (heights_ok is None or heights_ok[0] - TOP_HEIGHT_TOLERANCE_M
                                    <= tops[0].height_m <= heights_ok[1] + TOP_HEIGHT_TOLERANCE_M)
        if k == 0 and at_height and tops[0].short_side_m >= least_width_m:
            return candidates[0]  # the nearest shows a top of the class: it is the table
        areas.append(tops[0].area_m2 if tops and (k == 0 or at_height) else 0.0)
    best = int(np.argmax(areas))
    return candidates[best] if areas[best] > TOP_WINS_FACTOR * areas[0] else candidates[0]


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
    frame with its normal up (default: z = 0, the map plane). ``remove_walls``: drop the wall
    behind the object first (:func:`semmap.walls.background_walls`, fitted on the pixels around
    the box) with everything beyond it. The rest is :func:`object_in_box`'s.
    """
    floor = floor if floor is not None else Plane.horizontal()
    rng = rng if rng is not None else np.random.default_rng(0)
    box = box_points(depth_m, intrinsics, T_map_camera, track.xyxy_px, params, floor, depth_range_m, rng,
                     remove_walls)
    if box is None:
        return None
    return object_in_box(box, intrinsics, T_map_camera, track, class_cfg, params, floor, stamp_s, rng,
                         cluster_by=cluster_by, exclude_voxels_m=exclude_voxels_m,
                         same_object_as_m=same_object_as_m, shape_prior=shape_prior)


def object_in_box(
    box: BoxPoints,
    intrinsics: CameraIntrinsics,
    T_map_camera: Transform,
    track: Track,
    class_cfg: ClassConfig,
    params: GeometryConfig,
    floor: Plane,
    stamp_s: float,
    rng: np.random.Generator,
    *,
    cluster_by: Literal["box", "voxels"] = "box",
    exclude_voxels_m: NDArray[np.float64] | None = None,
    same_object_as_m: NDArray[np.float64] | None = None,
    shape_prior: bool = True,
) -> ObjectObservation | None:
    """The object among a box's points (:func:`semmap.box_points.box_points`), or None when fewer than
    ``min_cluster_points`` voxels of it remain (an empty, distant or all-floor box).

    ``class_cfg.hollow`` decides whether a top plane is searched. ``cluster_by``: "box" picks
    the nearest large cluster spanning the box (see :func:`_pick_cluster`); "voxels" the
    cluster with most voxels (Open3D's usual choice after ``cluster_dbscan``, for comparisons).
    ``exclude_voxels_m`` (K, 3): points of other objects (voxel centres, map frame); the box's
    points in their voxels are not this object's. ``same_object_as_m`` (K, 3): the object is
    the cluster holding most of these points (a second look at the same object, see
    :mod:`semmap.frame_objects`). ``shape_prior``: apply the class's shape prior
    (:mod:`semmap.shape_prior`).
    """
    tab = box.table
    if exclude_voxels_m is not None and len(exclude_voxels_m):
        mine = _without_other_objects(tab, exclude_voxels_m, params)
        if mine is None:
            return None  # the box shows other objects only
        tab = mine
    clusters = _cluster(tab, box.stride_px, intrinsics, params)
    best = _choose_cluster(clusters, tab, box.window_px, class_cfg, params, floor, cluster_by, same_object_as_m,
                           shape_prior)
    obj_idx = np.flatnonzero(clusters.vox_label == best)
    if (cluster_by == "box" and clusters.eps_m > params.cluster_distance_m
            and len(obj_idx) >= 2 * params.min_cluster_points
            and (not shape_prior or (class_cfg.shape == "free" and class_cfg.hollow == "none"))):
        # A distance grown with range also spans the depth noise in the gap to a neighbour. Only
        # for solid objects without a shape prior (a sofa): a chair's thin back is as sparse as
        # that noise, and a table's pick weighs its top, not the nearest part.
        obj_idx = _unbridged(obj_idx, clusters, tab, box.window_px, params, same_object_as_m)
    if shape_prior and class_cfg.shape != "free":
        part = _this_objects_part(clusters, obj_idx, class_cfg, params, floor)
        if part is None:
            return None  # the box shows another object's top only
        obj_idx = part
    if len(obj_idx) < params.min_cluster_points:
        return None
    return _observation(obj_idx, clusters, tab, T_map_camera, track, class_cfg, params, floor, stamp_s, rng,
                        shape_prior, box.image_size_px)


def _observation(
    obj_idx: NDArray[np.intp], clusters: _Clusters, tab: NDArray[np.float64], T_map_camera: Transform, track: Track,
    class_cfg: ClassConfig, params: GeometryConfig, floor: Plane, stamp_s: float, rng: np.random.Generator,
    shape_prior: bool, image_size_px: tuple[int, int],
) -> ObjectObservation:
    """Steps 5-6 for the object's voxels ``obj_idx``: the observation with its heights above the
    floor, top plane and footprint (map frame)."""
    obj_vox = clusters.vox[obj_idx]
    in_obj = np.zeros(len(clusters.vox), dtype=bool)
    in_obj[obj_idx] = True
    on_obj = np.flatnonzero(in_obj[clusters.inverse])
    z_min, z_max = _height_range(tab[HEIGHT_ROW, on_obj], tab[CLEARANCE_ROW, on_obj], params)
    top_plane, top_height = _top_plane(obj_vox, class_cfg, params, floor, rng)
    if shape_prior and class_cfg.shape == "table" and top_height is not None:
        z_min = 0.0  # a table stands on the floor on legs the chairs round it often hide
    centroid = obj_vox.mean(axis=0)
    # Projection onto the map plane: all object points, the top among them, so the space
    # between legs lies inside the hull.
    footprint = simplify_polygon(convex_footprint(obj_vox[:, :2], min_width_m=params.voxel_size_m),
                                 params.voxel_size_m / 2)
    cam_pos = T_map_camera[:3, 3]
    return ObjectObservation(
        track_id=track.track_id, class_name=track.class_name, score=float(track.score), stamp_s=float(stamp_s),
        centroid_map_m=(float(centroid[0]), float(centroid[1]), float(centroid[2])),
        footprint_xy_m=footprint, points_xy_m=obj_vox[:, :2].copy(),
        z_min_m=z_min, z_max_m=z_max, n_points=len(on_obj), n_voxels=len(obj_vox),
        range_m=float(np.linalg.norm(centroid - cam_pos)), top_plane=top_plane, top_height_m=top_height,
        at_image_edge=_touches_image_edge(track.xyxy_px, image_size_px),
        camera_xy_m=(float(cam_pos[0]), float(cam_pos[1])), voxels_map_m=obj_vox,
    )


def _without_other_objects(
    tab: NDArray[np.float64], exclude_voxels_m: NDArray[np.float64], params: GeometryConfig,
) -> NDArray[np.float64] | None:
    """The columns of ``tab`` outside the voxels of ``exclude_voxels_m`` (K, 3), or None when
    fewer than ``min_cluster_points`` remain."""
    mine = ~within_a_voxel(tab[:3].T, exclude_voxels_m, params.voxel_size_m)
    if np.count_nonzero(mine) < params.min_cluster_points:
        return None
    return tab[:, mine]


@dataclass(frozen=True, eq=False)
class _Clusters:
    """A box's points voxelized and clustered: ``vox`` (M, 3) voxel centres, ``inverse`` (N,)
    each point's voxel, ``vox_label`` (M,) cluster per voxel ordered by size, ``eps_m`` the
    linkage distance used."""

    vox: NDArray[np.float64]
    inverse: NDArray[np.int64]
    vox_label: NDArray[np.int64]
    eps_m: float


def _cluster(tab: NDArray[np.float64], stride_px: int, intrinsics: CameraIntrinsics,
             params: GeometryConfig) -> _Clusters:
    """Voxel downsampling, then single linkage at ``cluster_distance_m`` or
    ``cluster_pixel_gaps`` sampled-pixel spacings at the box's far range, whichever is larger."""
    vox, inverse = voxel_downsample(tab[:3].T, params.voxel_size_m)  # (M, 3), (N,)
    spacing_m = stride_px * _quantile_lower(tab[RANGE_ROW], 0.9) / min(intrinsics.fx_px, intrinsics.fy_px)
    eps = max(params.cluster_distance_m, params.cluster_pixel_gaps * spacing_m)
    return _Clusters(vox, inverse, euclidean_clusters(vox, eps), eps)


def _choose_cluster(
    clusters: _Clusters, tab: NDArray[np.float64], window: tuple[int, int, int, int], class_cfg: ClassConfig,
    params: GeometryConfig, floor: Plane, cluster_by: Literal["box", "voxels"],
    same_object_as_m: NDArray[np.float64] | None, shape_prior: bool,
) -> int:
    """The label of the cluster that is the object (see :func:`object_in_box`)."""
    vox, vox_label = clusters.vox, clusters.vox_label
    if cluster_by == "voxels":
        return 0  # labels are ordered by voxel count
    if same_object_as_m is not None and len(same_object_as_m):
        # The object seen before (this box's first look, less other objects' points): the
        # cluster holding most of it, not whatever now spans the box best.
        ours = in_sorted(voxel_keys(vox, params.voxel_size_m),
                         np.sort(voxel_keys(same_object_as_m, params.voxel_size_m)))
        if not ours.any():
            return 0
        return int(np.argmax(np.bincount(vox_label[ours], minlength=int(vox_label.max()) + 1)))
    candidates = _pick_cluster(vox_label[clusters.inverse], tab[RANGE_ROW], tab[PIXEL_U_ROW:].T.astype(np.int64), window,
                               params.cluster_min_pixel_frac, params.cluster_min_box_cover)
    if shape_prior and class_cfg.shape == "table" and len(candidates) > 1:
        return _widest_top(vox, vox_label, floor.signed_distance_m(vox), candidates, class_cfg, params)
    return candidates[0]


def _unbridged(
    obj_idx: NDArray[np.int64], clusters: _Clusters, tab: NDArray[np.float64], window: tuple[int, int, int, int],
    params: GeometryConfig, same_object_as_m: NDArray[np.float64] | None,
) -> NDArray[np.int64]:
    """The chosen cluster's voxels ``obj_idx`` less what noise in a gap joined to them: of its
    dense parts (:func:`semmap.noise_bridges.dense_parts`) the one holding most of
    ``same_object_as_m``, else :func:`_pick_cluster`'s (a sofa's, not the coffee table's in
    front of its lower half). One part: the cluster as it was."""
    vox = clusters.vox
    parts = dense_parts(vox[obj_idx], clusters.eps_m)
    if parts.max(initial=-1) < 1:
        return obj_idx
    if same_object_as_m is not None and len(same_object_as_m):
        ours = in_sorted(voxel_keys(vox[obj_idx], params.voxel_size_m),
                         np.sort(voxel_keys(same_object_as_m, params.voxel_size_m)))
        held = np.bincount(parts[ours & (parts >= 0)], minlength=int(parts.max()) + 1)
        return obj_idx[parts == int(np.argmax(held))]
    part_of_vox = np.full(len(vox), -1, dtype=np.int64)
    part_of_vox[obj_idx] = parts
    point_part = part_of_vox[clusters.inverse]
    on = point_part >= 0
    range_m = tab[RANGE_ROW]
    chosen = _pick_cluster(point_part[on], range_m[on], tab[PIXEL_U_ROW:].T.astype(np.int64)[on], window,
                           params.cluster_min_pixel_frac, params.cluster_min_box_cover)[0]
    # Only what stands in front of the object is another one; parts behind stay its own.
    med = np.array([np.median(range_m[point_part == k]) if np.any(point_part == k) else -np.inf
                    for k in range(int(parts.max()) + 1)])
    if np.any(med > med[chosen]):
        return obj_idx
    return obj_idx[parts == chosen]


def _this_objects_part(
    clusters: _Clusters, obj_idx: NDArray[np.intp], class_cfg: ClassConfig, params: GeometryConfig, floor: Plane,
) -> NDArray[np.intp] | None:
    """Of the chosen cluster's voxels (indices ``obj_idx``), those the class's shape says are
    this object (touching furniture is one cluster), or None when too few are."""
    obj_vox = clusters.vox[obj_idx]
    keep = shape_mask(obj_vox, floor.signed_distance_m(obj_vox), class_cfg.shape, params.voxel_size_m,
                      params.min_plane_points)
    if keep.sum() < params.min_cluster_points:
        return None
    if keep.all():
        return obj_idx
    piece = euclidean_clusters(obj_vox[keep], clusters.eps_m)  # what is left may fall apart
    return obj_idx[keep][piece == 0]


def _height_range(heights_m: NDArray[np.float64], clearance_m: NDArray[np.float64],
                  params: GeometryConfig) -> tuple[float, float]:
    """(z_min, z_max) above the floor of an object's points (heights and floor clearances)."""
    lowest = int(np.argmin(heights_m))
    z_max = _quantile_lower(heights_m, params.height_quantile)
    z_min = float(heights_m[lowest])
    # Standing on the floor: its lowest points were cut with the floor (up to the clearance at
    # its lowest point), so it reaches z = 0.
    if z_min <= float(clearance_m[lowest]) + params.voxel_size_m:
        z_min = 0.0
    return z_min, z_max


def _top_plane(obj_vox: NDArray[np.float64], class_cfg: ClassConfig, params: GeometryConfig, floor: Plane,
               rng: np.random.Generator) -> tuple[Plane | None, float | None]:
    """A hollow-bottom class's near-horizontal top plane (RANSAC) and its median height above
    the floor, or (None, None)."""
    if class_cfg.hollow == "none":
        return None, None
    fit = fit_plane(
        obj_vox, params.ransac_distance_m, params.ransac_iterations, rng,
        up=floor.normal_array, max_tilt_rad=math.radians(params.plane_max_tilt_deg),
        min_inliers=params.min_plane_points,
    )
    if fit is None:
        return None, None
    return fit.plane, _median(floor.signed_distance_m(obj_vox[fit.inliers]))


def _touches_image_edge(xyxy_px: tuple[float, float, float, float], image_size_px: tuple[int, int]) -> bool:
    """The box is within ``_EDGE_MARGIN_PX`` of the image border (so it may be cut by it)."""
    u0, v0, u1, v1 = xyxy_px
    w, h = image_size_px
    m = _EDGE_MARGIN_PX
    return bool(u0 <= m or v0 <= m or u1 >= w - m or v1 >= h - m)
