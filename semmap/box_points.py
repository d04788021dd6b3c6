"""A tracked detection's box as points in the map frame: steps 1-3 of
:func:`semmap.geometry.observe_object` (the object among them is :mod:`semmap.geometry`'s).

1. The box, shrunk by ``box_shrink_frac`` on each side (box edges leak background), is
   back-projected through the pinhole model; large boxes are sampled with a pixel stride so at
   most ``max_box_points`` pixels are used. Invalid depth never becomes a point.
2. Points go to the map frame with the full rigid transform ``T_map_camera`` (which callers
   compose as ``T_map_body @ T_body_camera``, in SE(3)).
3. Points within ``floor_clearance_m`` of the floor plane are dropped: the floor is not part
   of any object, and it would join every leg into one cluster with the room.
   The wall behind the object goes too, with everything beyond it: a vertical plane fitted
   (:func:`semmap.walls.background_walls`) on a ring of pixels just outside the box, accepted only when
   nothing of the ring or the box stands behind it and it faces the camera. A chair a few
   centimetres in front of a wall would otherwise be one cluster with the wall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.config import GeometryConfig
from semmap.frames import Transform
from semmap.pointcloud import window_points_map
from semmap.ransac import Plane
from semmap.types import CameraIntrinsics
from semmap.walls import in_front_of_walls

__all__ = ["BoxPoints", "box_points", "shrink_box"]


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


@dataclass(frozen=True, eq=False)
class BoxPoints:
    """A box's depth as points: the first step of :func:`semmap.geometry.observe_object`, shared by every
    look at the box (see :mod:`semmap.frame_objects`).

    ``table`` (8, N): map x, y, z, height above the floor, camera z-depth, floor clearance,
    pixel u, v of the box's sampled pixels above the floor cut and in front of any wall behind
    the box (one row each, so each later filter is one gather). ``window_px``: the shrunk box
    sampled at ``stride_px``. ``image_size_px``: (width, height).
    """

    table: NDArray[np.float64]
    window_px: tuple[int, int, int, int]
    stride_px: int
    image_size_px: tuple[int, int]


def box_points(
    depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: Transform,
    xyxy_px: tuple[float, float, float, float], params: GeometryConfig, floor: Plane,
    depth_range_m: tuple[float, float], rng: np.random.Generator, remove_walls: bool = True,
) -> BoxPoints | None:
    """The points of a box above the floor cut, less the wall behind it and all beyond
    (:func:`semmap.walls.in_front_of_walls`); None when too few remain for an object."""
    H, W = np.asarray(depth_m).shape
    window = shrink_box(xyxy_px, params.box_shrink_frac, W, H)
    u0, v0, u1, v1 = window
    area = max(0, u1 - u0) * max(0, v1 - v0)
    if area == 0:
        return None
    stride = max(1, int(math.ceil(math.sqrt(area / params.max_box_points))))
    tab, n_all = window_points_map(
        depth_m, intrinsics, depth_range_m[0], depth_range_m[1], window, stride, T_map_camera,
        floor.normal_array, floor.offset_m, params.floor_clearance_m, params.floor_clearance_per_m2,
    )
    if n_all < params.min_cluster_points or tab.shape[1] < params.min_cluster_points:
        return None
    if remove_walls:
        front = in_front_of_walls(tab, depth_m, intrinsics, T_map_camera, xyxy_px, params, floor,
                                  depth_range_m, rng)
        if front is not None and not front.all():
            if np.count_nonzero(front) < params.min_cluster_points:
                return None  # the box shows the wall only
            tab = tab[:, front]
    return BoxPoints(tab, window, stride, (W, H))
