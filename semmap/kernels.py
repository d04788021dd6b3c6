"""Compile the numba kernels of the per-frame map update before the first frame needs them.

Object geometry (:mod:`semmap.pointcloud`, :mod:`semmap.clustering`, :mod:`semmap.ransac`,
the wall search in :mod:`semmap.walls`, the surface search in :mod:`semmap.shape_prior`),
the object map's footprint overlaps (:mod:`semmap.polygons`) and the band scan
(:mod:`semmap.scan`) run numba-compiled kernels. numba compiles each on its first call, about 8 s for all of them on
this 2-core machine, and caches the machine code (``cache=True``: ``__pycache__`` beside
the modules, numba's per-user cache where that is read-only, or ``$NUMBA_CACHE_DIR``);
loading them from the cache takes about 0.3 s. :func:`warm_up` pays either cost up front,
on a small synthetic view, so a process that calls it at start does not stall on its first
real frame.
"""

from __future__ import annotations

import time

import numpy as np

from semmap.config import GeometryConfig, default_classes
from semmap.costmap import VerticalBand
from semmap.geometry import observe_object
from semmap.polygons import convex_intersection
from semmap.scan import extract_band_scan
from semmap.types import CameraIntrinsics, Track

#: Optical camera -> map for a camera looking along map +x, 1 m above the floor.
_T_MAP_CAMERA = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]]
)


def warm_up() -> float:
    """Run object geometry (a hollow object before a wall, so every kernel runs), the band
    scan once on a synthetic 64 x 48 float32 depth image and one footprint overlap; returns
    the seconds it took (the compile or cache-load time)."""
    t0 = time.perf_counter()
    K = CameraIntrinsics(50.0, 50.0, 32.0, 24.0, 64, 48)
    depth = np.full((48, 64), 3.0, np.float32)  # a wall 3 m ahead
    depth[14:40, 18:46] = 2.0  # the object, 1 m in front of it
    track = Track(1, (18.0, 14.0, 46.0, 40.0), 0.9, "coffee_table")
    by_name = {c.name: c for c in default_classes()}
    observe_object(depth, K, _T_MAP_CAMERA, track, by_name["coffee_table"], GeometryConfig(),
                   depth_range_m=(0.3, 6.0), rng=np.random.default_rng(0))
    extract_band_scan(depth, K, _T_MAP_CAMERA, VerticalBand(0.3, 0.9))
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    convex_intersection(square, square + 0.5)
    return time.perf_counter() - t0
