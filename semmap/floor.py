"""The floor of one view from gravity: only its height is estimated.

The pose carries the gravity direction (map z is up: the autopilot's attitude on the drone, the
floor-aligned map frame of a recording), so the floor's tilt is never fitted per view, where a
floor that is a small part of the image next to larger bed and table tops could tilt the fit by
degrees and every height in the view with it. :func:`view_floor_height_m` takes the view's
points near the map's floor height and returns the height of the lowest horizontal layer that
holds enough of them; a view that shows no such layer has no floor (None), and its heights are
not trusted.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from semmap.frames import Transform
from semmap.pointcloud import backproject
from semmap.types import CameraIntrinsics

__all__ = ["FLOOR_SEARCH_M", "view_floor_height_m"]

#: The floor of a view is searched this far above and below the map's floor height (metres):
#: the map frame's floor is known to within pose drift, and beyond it lie seats and steps.
FLOOR_SEARCH_M = 0.2
#: Height layers of the search (metres): about the depth noise of the floor at 4 m.
FLOOR_BIN_M = 0.02
#: Floor points are taken only this close to the camera (metres), where depth is accurate.
FLOOR_MAX_RANGE_M = 4.0
#: The floor layer holds at least this share of the view's sampled points, and at least
#: ``FLOOR_MIN_POINTS`` of them (noise below the floor never does).
FLOOR_MIN_FRAC = 0.02
FLOOR_MIN_POINTS = 40
#: Points sampled per view (the depth image is strided to about this many).
FLOOR_SAMPLES = 6000


def view_floor_height_m(
    depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: Transform,
    depth_range_m: tuple[float, float], prior_height_m: float = 0.0,
) -> float | None:
    """The floor's height (map z, metres) in one view, or None when the view shows no floor.

    ``T_map_camera`` (4, 4): optical camera -> a map frame whose z is up. The floor is the lowest
    ``FLOOR_BIN_M`` layer within ``FLOOR_SEARCH_M`` of ``prior_height_m`` holding enough of the
    view's points (see the module constants); its height is their median z.
    """
    h, w = np.asarray(depth_m).shape
    stride = max(1, int(round(math.sqrt(h * w / FLOOR_SAMPLES))))
    lo_m, hi_m = depth_range_m
    pts_cam, _ = backproject(depth_m, intrinsics, lo_m, min(hi_m, FLOOR_MAX_RANGE_M), stride_px=stride)
    if len(pts_cam) == 0:
        return None
    R = np.asarray(T_map_camera, dtype=np.float64)[:3, :3]
    z = pts_cam.astype(np.float64) @ R[2] + float(T_map_camera[2, 3])
    low = prior_height_m - FLOOR_SEARCH_M
    z_near = z[(z >= low) & (z < prior_height_m + FLOOR_SEARCH_M)]
    need = max(FLOOR_MIN_POINTS, FLOOR_MIN_FRAC * len(z))
    if len(z_near) < need:
        return None
    n_bins = int(math.ceil(2 * FLOOR_SEARCH_M / FLOOR_BIN_M))
    counts, edges = np.histogram(z_near, bins=n_bins, range=(low, low + n_bins * FLOOR_BIN_M))
    # Two adjacent layers, so a floor straddling a layer edge is not split in half.
    pair = counts + np.concatenate([counts[1:], [0]])
    found = np.nonzero(pair >= need)[0]
    if len(found) == 0:
        return None
    # The first supported layer may be the lower tail of a noisy floor: the median of the
    # points around it, taken again around that median, is the floor's middle.
    k = int(found[0])
    mid = float(np.median(z_near[(z_near >= edges[k] - FLOOR_BIN_M) & (z_near < edges[k] + 4 * FLOOR_BIN_M)]))
    return float(np.median(z_near[np.abs(z_near - mid) <= 2 * FLOOR_BIN_M]))
