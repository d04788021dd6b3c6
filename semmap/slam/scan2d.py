"""The SLAM's input: one 2D scan in the gravity-aligned, body-centred frame.

The frame is the body frame (FLU) rotated so its z axis is vertical: x points along the
vehicle's heading projected on the floor, the origin is the vehicle's centre. The autopilot's
roll and pitch are removed when the scan is extracted from depth
(:func:`level_scan_from_depth`), so the scan matcher only estimates x, y and yaw.

A scan is a fan of rays: hits (obstacle points, what the matcher aligns) and the free part of
each ray (what a submap clears). A plain point set becomes rays from the sensor origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import VerticalBand
from semmap.errors import FrameError
from semmap.frames import rotation_from_rpy
from semmap.scan import BandScan, extract_band_scan
from semmap.slam.pose2d import Pose2, transform_xy
from semmap.types import CameraIntrinsics


@dataclass(frozen=True, eq=False)
class LevelScan:
    """Rays in the gravity-aligned body frame (metres).

    ``origin_xy_m`` (2,) sensor position; ``near_xy_m``/``far_xy_m`` (N, 2) free part of each
    ray; ``hit_xy_m`` (N, 2) obstacle point where ``is_hit`` (N,); ``valid`` (N,) the ray
    carries information.
    """

    origin_xy_m: NDArray[np.float64]
    near_xy_m: NDArray[np.float64]
    far_xy_m: NDArray[np.float64]
    hit_xy_m: NDArray[np.float64]
    is_hit: NDArray[np.bool_]
    valid: NDArray[np.bool_]

    @property
    def hits_xy_m(self) -> NDArray[np.float64]:
        """(K, 2) obstacle points (what the scan matcher aligns)."""
        return self.hit_xy_m[self.is_hit & self.valid]

    @classmethod
    def from_points(cls, points_xy_m: NDArray[np.floating],
                    origin_xy_m: tuple[float, float] = (0.0, 0.0)) -> "LevelScan":
        """Rays from ``origin_xy_m`` to each of the (N, 2) points, every point a hit. Points
        should be ordered by bearing (consecutive rays bound the free polygon)."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise FrameError("scan points must be finite")
        o = np.asarray(origin_xy_m, dtype=np.float64).reshape(2)
        n = len(pts)
        return cls(o, np.tile(o, (n, 1)), pts.copy(), pts.copy(), np.ones(n, bool), np.ones(n, bool))

    @classmethod
    def from_ranges(cls, ranges_m: NDArray[np.floating], angles_rad: NDArray[np.floating],
                    max_range_m: float = np.inf) -> "LevelScan":
        """A lidar-style scan: (N,) ranges at (N,) bearings (radians, 0 = ahead, counter-
        clockwise) from the body centre. Non-finite or out-of-range rays are invalid."""
        r = np.asarray(ranges_m, dtype=np.float64).reshape(-1)
        a = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
        if r.shape != a.shape:
            raise FrameError(f"ranges {r.shape} and angles {a.shape} differ in length")
        ok = np.isfinite(r) & (r > 0.0) & (r <= max_range_m)
        rr = np.where(ok, r, 0.0)
        pts = np.stack([rr * np.cos(a), rr * np.sin(a)], axis=1)
        o = np.zeros(2)
        return cls(o, np.zeros_like(pts), pts, pts.copy(), ok.copy(), ok)

    @classmethod
    def from_band_scan(cls, scan: BandScan) -> "LevelScan":
        """A :class:`BandScan` that was extracted in the level body frame (not the map)."""
        return cls(scan.origin_xy_m.copy(), scan.near_xy_m, scan.far_xy_m, scan.hit_xy_m,
                   scan.is_hit & scan.valid, scan.valid)

    def transformed(self, pose: Pose2) -> "LevelScan":
        """The rays in the frame where the scan's body sits at ``pose`` (x, y, yaw)."""
        return LevelScan(
            transform_xy(pose, self.origin_xy_m)[0], transform_xy(pose, self.near_xy_m),
            transform_xy(pose, self.far_xy_m), transform_xy(pose, self.hit_xy_m),
            self.is_hit, self.valid,
        )


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
) -> LevelScan:
    """The altitude-band scan of an (H, W) depth image (the same extraction the occupancy
    grid uses, :func:`semmap.scan.extract_band_scan`) in the gravity-aligned body frame.

    ``band``: heights above the floor (metres); ``altitude_m``: the body's height above the
    floor; ``roll_rad``/``pitch_rad``: the autopilot's attitude (FLU, Z-Y-X Euler)."""
    T = T_level_camera(T_body_camera, roll_rad, pitch_rad, altitude_m)
    bs = extract_band_scan(depth_m, intrinsics, T, band, min_depth_m=min_depth_m,
                           max_depth_m=max_depth_m, stride_px=stride_px, stamp_s=stamp_s)
    return LevelScan.from_band_scan(bs)
