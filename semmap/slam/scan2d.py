"""The SLAM's input: the band scan (:class:`semmap.scan.BandScan`) of a depth image in the
gravity-aligned, body-centred frame.

The frame is the body frame (FLU) rotated so its z axis is vertical: x points along the
vehicle's heading projected on the floor, the origin is the vehicle's centre. The autopilot's
roll and pitch are removed when the scan is extracted from depth
(:func:`level_scan_from_depth`), so the scan matcher only estimates x, y and yaw. The hits
are what the matcher aligns, the free part of each ray what a submap clears.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import VerticalBand
from semmap.frames import rotation_from_rpy
from semmap.scan import BandScan, extract_band_scan
from semmap.types import CameraIntrinsics


def T_level_camera(  # noqa: N802 - frame names
    T_body_camera: NDArray[np.float64], roll_rad: float, pitch_rad: float, altitude_m: float,
) -> NDArray[np.float64]:
    """(4, 4) optical camera -> gravity-aligned body frame lifted to ``altitude_m`` above the
    floor: the body's roll and pitch (from the autopilot's attitude) are applied, its yaw
    is not."""
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(roll_rad, pitch_rad, 0.0)
    T[2, 3] = altitude_m
    return T @ np.asarray(T_body_camera, dtype=np.float64)


def level_scan_from_depth(
    depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics,
    T_body_camera: NDArray[np.float64], roll_rad: float, pitch_rad: float, altitude_m: float,
    band: VerticalBand, min_depth_m: float = 0.3, max_depth_m: float = 6.0, stride_px: int = 2,
    stamp_s: float = 0.0,
) -> BandScan:
    """The altitude-band scan of an (H, W) depth image (the same extraction the occupancy
    grid uses, :func:`semmap.scan.extract_band_scan`) in the gravity-aligned body frame,
    with each hit re-centred on its surface (``recentre_hit``) for the scan matcher.

    ``band``: heights above the floor (metres); ``altitude_m``: the body's height above the
    floor; ``roll_rad``/``pitch_rad``: the autopilot's attitude (FLU, Z-Y-X Euler)."""
    T = T_level_camera(T_body_camera, roll_rad, pitch_rad, altitude_m)
    return extract_band_scan(depth_m, intrinsics, T, band, min_depth_m=min_depth_m,
                             max_depth_m=max_depth_m, stride_px=stride_px, stamp_s=stamp_s,
                             recentre_hit=True)
