"""All boxes of one frame together: which object a point belongs to when boxes overlap.

:func:`semmap.geometry.observe_object` sees one box at a time, and a box holds more than its
object where furniture touches or stands in front: a table's box holds the chairs in front of
it, a chair behind a table holds the table top. :func:`observe_frame` observes every box, then
gives each point to the object the other boxes of the frame say it belongs to, and observes a
box again without the points that are not its own:

* **a nearer object**: a point in the box's cluster that is also in the cluster of another,
  overlapping box whose object is nearer the camera (by ``NEARER_BY_M``) belongs to that
  object (it stands in front; this box sees it only where it covers the farther one);
* **nothing of its own**: a box whose first look found no object of its class (a chair's
  box holding only the table top in front of it) is looked at again without the other
  overlapping boxes' objects;
* **another box's object**: a box whose cluster is mostly the object of another box that sees
  more of it (the table top filling the lower part of a box round a chair behind the table),
  or that is not cut by the image border while this one is (a table running out of the
  image, with a chair in front of it), shows that object: this box's object is what remains
  behind it, or nothing;
* **a neighbour of the same kind**: where none of these applies, two overlapping boxes of the
  same shape class (chairs side by side at a table, seen along the row) often hold one
  cluster that spans both objects. Points that only one of the two boxes holds are that
  object's; each point the two boxes share goes to the object whose own points are nearest.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from semmap.box_points import BoxPoints, box_points
from semmap.camera_view import cut_edges, depth_frame_px
from semmap.config import ClassConfig, GeometryConfig
from semmap.frames import Transform
from semmap.geometry import ObjectObservation, object_in_box
from semmap.pointcloud import project_map_points
from semmap.ransac import Plane
from semmap.types import CameraIntrinsics, Track
from semmap.voxels import within_a_voxel

__all__ = ["observe_frame"]

#: Another box's object is nearer when its range is smaller by at least this (metres).
NEARER_BY_M = 0.2
#: A box's cluster "is" another box's object when this share of its voxels is.
SHARED_FRAC = 0.5
#: Points of other objects are taken out only when they are at least this share of the box's
#: object (a few shared voxels at a contact line change nothing).
MIN_FOREIGN_FRAC = 0.1


def _boxes_overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _bounds_meet(a_m: NDArray[np.float64], b_m: NDArray[np.float64], margin_m: float) -> bool:
    """The bounding boxes of two point sets (N, 3), (M, 3) meet within ``margin_m``."""
    return bool(np.all(a_m.min(axis=0) <= b_m.max(axis=0) + margin_m)
                and np.all(b_m.min(axis=0) <= a_m.max(axis=0) + margin_m))


def observe_frame(
    depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: Transform,
    tracks: Sequence[Track], classes: Mapping[str, ClassConfig], params: GeometryConfig,
    floor: Plane | None = None, depth_range_m: tuple[float, float] = (0.0, math.inf), stamp_s: float = 0.0,
    rng: np.random.Generator | None = None,
) -> list[ObjectObservation]:
    """The observations of one frame's tracks (see the module doc), in track order; tracks
    whose box holds no object of its own have none. ``classes``: class name -> its config."""
    rng = rng if rng is not None else np.random.default_rng(0)
    floor = floor if floor is not None else Plane.horizontal()
    # Each box's points once (back-projection and the wall behind it); every look reuses them.
    boxes = [box_points(depth_m, intrinsics, T_map_camera, tr.xyxy_px, params, floor, depth_range_m, rng)
             for tr in tracks]

    def observe(i: int, exclude: NDArray[np.float64] | None = None,
                same: NDArray[np.float64] | None = None) -> ObjectObservation | None:
        box: BoxPoints | None = boxes[i]
        if box is None:
            return None
        tr = tracks[i]
        return object_in_box(box, intrinsics, T_map_camera, tr, classes[tr.class_name], params, floor, stamp_s,
                             rng, exclude_voxels_m=exclude, same_object_as_m=same)

    first = [observe(i) for i in range(len(tracks))]
    out: list[tuple[int, ObjectObservation]] = []  # (box, observation)
    for i, (tr, o) in enumerate(zip(tracks, first, strict=True)):
        if o is None:
            # Nothing of its own at first look (a seat's box whose cluster was another object's
            # top, see semmap.shape_prior): it may be behind the other boxes' objects.
            if classes[tr.class_name].shape != "seat":
                continue
            others = [p.voxels_map_m for j, p in enumerate(first)
                      if j != i and p is not None and _boxes_overlap(tr.xyxy_px, tracks[j].xyxy_px)]
            behind = observe(i, np.concatenate(others)) if others else None
            if behind is not None:
                out.append((i, behind))
            continue
        foreign, shown = _foreign_objects(i, o, tracks, first, params.voxel_size_m)
        if not foreign:
            foreign = _same_kind_neighbours(i, o, tracks, first, classes, intrinsics, T_map_camera, params)
        if not foreign:
            out.append((i, o))
            continue
        # Showing another object: this box's own is whatever remains. Else it is the same
        # cluster as before, less the nearer objects' points.
        excluded = np.concatenate(foreign)
        same = None
        if not shown:
            same = o.voxels_map_m[~within_a_voxel(o.voxels_map_m, excluded, params.voxel_size_m)]
            if len(same) < params.min_cluster_points:
                continue  # it was the nearer object's points all along
        again = observe(i, excluded, same)
        if again is not None:
            out.append((i, again))
    if not out:
        return []
    frame = depth_frame_px(depth_m, *depth_range_m)
    return [replace(o, footprint_edge_cut=cut_edges(o.footprint_xy_m, o.voxels_map_m, intrinsics, T_map_camera,
                                                     frame, params.voxel_size_m, _stride(boxes[i])))
            for i, o in out]


def _stride(box: BoxPoints | None) -> int:
    return box.stride_px if box is not None else 1


def _foreign_objects(
    i: int, o: ObjectObservation, tracks: Sequence[Track], first: Sequence[ObjectObservation | None],
    voxel_size_m: float,
) -> tuple[list[NDArray[np.float64]], bool]:
    """(voxels (K, 3) map frame, shown): the other boxes' objects whose points in box ``i``'s
    first look ``o`` are not its own, and whether ``o`` is mostly one of them (it shows it)."""
    tr = tracks[i]
    foreign: list[NDArray[np.float64]] = []
    shown = False
    for j, (other, p) in enumerate(zip(tracks, first, strict=True)):
        if j == i or p is None or not _boxes_overlap(tr.xyxy_px, other.xyxy_px):
            continue
        nearer = p.range_m < o.range_m - NEARER_BY_M
        fuller = p.n_voxels > o.n_voxels or (o.at_image_edge and not p.at_image_edge)
        if not (nearer or fuller) or not _bounds_meet(o.voxels_map_m, p.voxels_map_m, 2 * voxel_size_m):
            continue  # neither rule can apply: no need to look at the points
        frac = float(np.count_nonzero(within_a_voxel(o.voxels_map_m, p.voxels_map_m, voxel_size_m)))
        frac /= max(1, len(o.voxels_map_m))
        # Mostly another box's object, seen more fully there (more of it, or not cut).
        shows_other = frac >= SHARED_FRAC and fuller
        if (nearer and frac >= MIN_FOREIGN_FRAC) or shows_other:
            foreign.append(p.voxels_map_m)
            shown = shown or shows_other
    return foreign, shown


def _same_kind_neighbours(
    i: int, o: ObjectObservation, tracks: Sequence[Track], first: Sequence[ObjectObservation | None],
    classes: Mapping[str, ClassConfig], intrinsics: CameraIntrinsics, T_map_camera: Transform,
    params: GeometryConfig,
) -> list[NDArray[np.float64]]:
    """Voxels (K, 3) of box ``i``'s first look ``o`` that belong to a neighbour of the same
    shape class (see the module doc): a shared point goes to the object whose points seen in
    one box only are nearest to it."""
    tr = tracks[i]
    kind = classes[tr.class_name].shape
    foreign: list[NDArray[np.float64]] = []
    for j, (other, p) in enumerate(zip(tracks, first, strict=True)):
        if (j == i or p is None or classes[other.class_name].shape != kind
                or not _boxes_overlap(tr.xyxy_px, other.xyxy_px)
                or not _bounds_meet(o.voxels_map_m, p.voxels_map_m, 2 * params.voxel_size_m)):
            continue
        pts, index = np.unique(np.concatenate([o.voxels_map_m, p.voxels_map_m]), axis=0, return_inverse=True)
        u, v, z = project_map_points(pts, intrinsics, T_map_camera)
        in_i, in_j = _in_box(u, v, z, tr.xyxy_px), _in_box(u, v, z, other.xyxy_px)
        own_i, own_j = pts[in_i & ~in_j], pts[in_j & ~in_i]
        if len(own_i) < params.min_cluster_points or len(own_j) < params.min_cluster_points:
            continue  # one box inside the other: nothing tells the two apart
        shared = o.voxels_map_m[in_j[index.reshape(-1)[: len(o.voxels_map_m)]]]
        if len(shared) < MIN_FOREIGN_FRAC * len(o.voxels_map_m):
            continue
        d_i, _ = cKDTree(own_i).query(shared)
        d_j, _ = cKDTree(own_j).query(shared)
        theirs = shared[d_j < d_i]
        if len(theirs):
            foreign.append(theirs)
    return foreign


def _in_box(u: NDArray[np.float64], v: NDArray[np.float64], z: NDArray[np.float64],
            xyxy_px: tuple[float, float, float, float]) -> NDArray[np.bool_]:
    """(N,) which projected points (:func:`~semmap.pointcloud.project_map_points`) lie in
    front of the camera and inside the image box ``xyxy_px``."""
    u0, v0, u1, v1 = xyxy_px
    return np.asarray((z > 0) & (u >= u0) & (u < u1) & (v >= v0) & (v < v1), dtype=bool)
