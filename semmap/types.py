"""Values that cross stage boundaries: intrinsics, frames, detections, tracks.

All are frozen dataclasses. Array fields document their shape and dtype; images are
row-major (H, W). Pixel coordinates are (u right, v down) with the origin at the top-left
corner of the top-left pixel, boxes are ``xyxy_px = (u_min, v_min, u_max, v_max)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics for an image of ``width_px`` x ``height_px``."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int

    @property
    def K(self) -> NDArray[np.float64]:  # noqa: N802 - conventional name
        """(3, 3) camera matrix."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )

    @property
    def hfov_rad(self) -> float:
        return float(2.0 * np.arctan2(self.width_px / 2.0, self.fx_px))


@dataclass(frozen=True, eq=False)
class Frame:
    """One timestamped RGB-D frame.

    ``rgb``: (H, W, 3) uint8 in RGB order. ``depth_m``: (H, W) float32 metres, 0 or NaN where
    invalid. ``T_map_camera``: (4, 4) camera pose in the map frame (optical camera axes) when the
    source knows it (simulation, recorded ground truth, the autopilot's estimate), else None.
    ``T_odom_body``: (4, 4) body (FLU) pose in the autopilot's *odometry* frame, dead-reckoned
    from its velocity and yaw rate: continuous, and independent of the external vision the
    companion feeds back (the autopilot's position estimate is not: it fuses that vision).
    The SLAM's motion prior when present (:mod:`companion.service.localization`); None when
    the source has none.
    """

    stamp_s: float
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    intrinsics: CameraIntrinsics
    T_map_camera: NDArray[np.float64] | None = None
    index: int = 0
    #: Extra per-pixel data a simulated source provides (``"instance"``: (H, W) int32 object
    #: ids, 0 = none; ``"class"``: (H, W) int16 class index, -1 = none).
    masks: dict[str, NDArray[np.generic]] = field(default_factory=dict)
    T_odom_body: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class Detection:
    """One detector output in original-image pixels.

    ``class_name`` is our semantic class (after the config's class map), ``score`` in [0, 1].
    """

    xyxy_px: tuple[float, float, float, float]
    score: float
    class_name: str

    @property
    def area_px2(self) -> float:
        u0, v0, u1, v1 = self.xyxy_px
        return max(0.0, u1 - u0) * max(0.0, v1 - v0)


@dataclass(frozen=True)
class Track:
    """A confirmed tracker output: a detection with a persistent id."""

    track_id: int
    xyxy_px: tuple[float, float, float, float]
    score: float
    class_name: str
    #: Frames since the track was created.
    age_frames: int = 0
