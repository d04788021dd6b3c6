"""Our pose to PX4 as external vision (ODOMETRY), converting map/FLU to PX4's NED/FRD.

The map frame is ENU with the body FLU (see :mod:`semmap.frames`); PX4 wants the pose of the
FRD body in local NED. With ``R_ned_enu`` swapping x/y and flipping z, and ``R_flu_frd``
flipping y and z::

    p_ned = R_ned_enu @ p_map
    R_ned_frd = R_ned_enu @ R_map_flu @ R_flu_frd

The message is ODOMETRY with ``frame_id = MAV_FRAME_LOCAL_NED``, ``child_frame_id =
MAV_FRAME_BODY_FRD`` and ``estimator_type = MAV_ESTIMATOR_TYPE_VISION``; unknown velocities
and rates are NaN, which PX4 reads as "not provided". The pose covariance is finite on its
whole diagonal: EKF2 takes the x/y/z variances only when all three are finite (else it fuses
every axis at ``EKF2_EVP_NOISE``), and the roll/pitch/yaw ones likewise (``EKF2_EVA_NOISE``).
x, y and yaw carry what the 2D SLAM measures; height, roll and pitch are PX4's own (the SLAM
echoes them), so they carry a wide variance that says "not measured here" and EKF2 must not
fuse them (``EKF2_EV_CTRL`` without the vertical bit; EKF2 fuses no vision roll or pitch).

:class:`VisionStream` sends the latest pose at a fixed rate (30 Hz by default) from its own
task, stamped with the pose's capture time, so PX4's EKF2 fuses it at that time (it drops a
sample no newer than the one before, so repeats of a pose between camera frames cost
nothing). No pose, or a pose that is not from vision (the SLAM fell back to odometry), is not
sent: PX4 then coasts on its own estimate instead of being fed its own odometry back.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.background import end_task
from companion.errors import LinkError
from companion.mavlink.link import MavlinkLink
from semmap.frames import R_NED_ENU, Transform, ned_pose_from_map, quaternion_wxyz_from_rotation

log = logging.getLogger(__name__)

_NAN21 = [math.nan] * 21
#: Indices of the diagonal of MAVLink's upper-triangular 6x6 pose covariance (x y z roll pitch yaw).
_DIAG = (0, 6, 11, 15, 18, 20)
#: 1-sigma of what the pose echoes from PX4 (height, roll, pitch): wide, so that a fusion of
#: them, were it enabled, would hardly move PX4's own estimate that they came from.
ECHOED_HEIGHT_STD_M = 1.0
ECHOED_TILT_STD_RAD = math.radians(10.0)
#: The yaw 1-sigma sent when none is given (the SLAM's heading is still measured).
DEFAULT_YAW_STD_RAD = math.radians(5.0)


def pose_covariance(position_std_m: float | None, yaw_std_rad: float | None) -> list[float]:
    """ODOMETRY's ``pose_covariance`` (21, row-major upper triangle, NED/FRD) for a 2D pose:
    x and y variance ``position_std_m`` squared each (the SLAM's error is not directional in a
    way it reports), yaw variance ``yaw_std_rad`` squared (:data:`DEFAULT_YAW_STD_RAD` when
    None), height/roll/pitch the wide echoed variances, off-diagonals 0. Every diagonal entry
    is finite: one NaN among x/y/z (or roll/pitch/yaw) makes EKF2 drop all three for its
    ``EKF2_EVP_NOISE`` (``EKF2_EVA_NOISE``). All NaN ("unknown", MAVLink's rule: NaN first
    element) without a position standard deviation."""
    if position_std_m is None or not math.isfinite(position_std_m) or position_std_m <= 0.0:
        return list(_NAN21)
    if yaw_std_rad is None or not math.isfinite(yaw_std_rad) or yaw_std_rad <= 0.0:
        yaw_std_rad = DEFAULT_YAW_STD_RAD
    cov = [0.0] * 21
    var_xy = float(position_std_m) ** 2
    tilt_var = ECHOED_TILT_STD_RAD ** 2
    diag = (var_xy, var_xy, ECHOED_HEIGHT_STD_M ** 2, tilt_var, tilt_var, float(yaw_std_rad) ** 2)
    for k, v in zip(_DIAG, diag, strict=True):
        cov[k] = v
    return cov


def vision_odometry_message(
    link: MavlinkLink,
    T_map_body: Transform,
    time_usec: int,
    *,
    velocity_map_m_s: NDArray[np.float64] | None = None,
    quality_percent: int = 100,
    reset_counter: int = 0,
    position_std_m: float | None = None,
    yaw_std_rad: float | None = None,
) -> mavlink.MAVLink_odometry_message:
    """ODOMETRY for PX4's EKF2 external-vision fusion.

    ``T_map_body``: (4, 4) pose of the FLU body in the map frame. ``time_usec``: capture time
    of the pose (microseconds, our boot clock). ``velocity_map_m_s``: optional (3,) velocity
    in the map frame (sent in body FRD as PX4 expects), else NaN. ``reset_counter``: bump it
    when the pose jumps (relocalisation) so EKF2 resets instead of rejecting it.
    ``position_std_m``/``yaw_std_rad``: the pose's 1-sigma errors (see :func:`pose_covariance`).
    """
    p_ned, R_ned_frd = ned_pose_from_map(T_map_body)
    if velocity_map_m_s is not None:
        v_frd = R_ned_frd.T @ (R_NED_ENU @ np.asarray(velocity_map_m_s, dtype=np.float64))
        vx, vy, vz = (float(v) for v in v_frd)
    else:
        vx = vy = vz = math.nan
    return link.mav.odometry_encode(
        time_usec, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD,
        float(p_ned[0]), float(p_ned[1]), float(p_ned[2]), list(quaternion_wxyz_from_rotation(R_ned_frd)),
        vx, vy, vz, math.nan, math.nan, math.nan, pose_covariance(position_std_m, yaw_std_rad), _NAN21,
        reset_counter & 0xFF, mavlink.MAV_ESTIMATOR_TYPE_VISION, int(max(-1, min(100, quality_percent))),
    )


@dataclass(frozen=True)
class VisionPose:
    """One pose for the autopilot: ``stamp_s`` capture time (seconds, the clock PX4 is
    synchronised to), ``T_map_body`` (4, 4) FLU body in the map frame, ``quality_percent``
    (0-100), ``reset_counter`` (bump when the estimate jumps, e.g. after a loop closure),
    ``position_std_m``/``yaw_std_rad`` its 1-sigma errors (None: unknown)."""

    stamp_s: float
    T_map_body: Transform
    quality_percent: int = 100
    reset_counter: int = 0
    position_std_m: float | None = None
    yaw_std_rad: float | None = None


class VisionStream:
    """Streams the latest pose from ``source`` as external-vision ODOMETRY at ``rate_hz``
    (async context manager). ``source()`` returns a :class:`VisionPose` or None (nothing to
    send now). Counts what it sent (:attr:`sent`), how many of those were new poses
(:attr:`sent_new`: PX4's EKF2 fuses a stamp once), what it skipped (:attr:`skipped`) and how
often ``source()`` raised (:attr:`source_errors`);
:attr:`last_sent_s` / :attr:`last_new_s` are when it last sent a pose / a new pose
(``time.monotonic``, None before the first)."""

    def __init__(self, link: MavlinkLink, source: Callable[[], VisionPose | None], rate_hz: float = 30.0) -> None:
        if rate_hz <= 0.0:
            raise ValueError(f"vision rate must be > 0 Hz (got {rate_hz})")
        self.link = link
        self.source = source
        self.period_s = 1.0 / rate_hz
        self.sent = 0
        self.sent_new = 0
        self.skipped = 0
        self.source_errors = 0
        self.last_sent_s: float | None = None
        self.last_new_s: float | None = None
        #: Capture time of the last new pose sent (its ``stamp_s``; None before the first).
        self.last_new_stamp_s: float | None = None
        self._last_stamp_s = -math.inf
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> "VisionStream":
        self._task = asyncio.create_task(self._run(), name="vision-stream")
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        task, self._task = self._task, None
        await end_task(task, "the vision stream")

    def send_once(self) -> bool:
        """Send the current pose now; False when there is none, the source failed or the
        link refused it."""
        try:
            pose = self.source()
        except Exception:
            # PX4's only position source must outlive a failing pose source: nothing is sent
            # this tick (PX4's vision-loss failsafe acts if it persists), the stream runs on.
            self.source_errors += 1
            if self.source_errors == 1 or self.source_errors % 100 == 0:
                log.exception("external vision source failed (%d times); nothing sent this tick",
                              self.source_errors)
            return False
        if pose is None:
            self.skipped += 1
            return False
        try:
            self.link.send(vision_odometry_message(self.link, pose.T_map_body, int(pose.stamp_s * 1e6),
                                                   quality_percent=pose.quality_percent,
                                                   reset_counter=pose.reset_counter,
                                                   position_std_m=pose.position_std_m,
                                                   yaw_std_rad=pose.yaw_std_rad))
        except (LinkError, ValueError) as exc:
            self.skipped += 1
            if self.skipped % 100 == 1:
                log.warning("external vision not sent (%d so far): %s", self.skipped, exc)
            return False
        self.sent += 1
        self.last_sent_s = time.monotonic()
        if pose.stamp_s > self._last_stamp_s:
            self.sent_new += 1
            self.last_new_s = self.last_sent_s
            self.last_new_stamp_s = pose.stamp_s
            self._last_stamp_s = pose.stamp_s
        return True

    async def _run(self) -> None:
        next_t = time.monotonic()
        while True:
            self.send_once()
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay < 0.0:  # late (a busy loop): keep the rate, do not burst
                next_t = time.monotonic()
                delay = 0.0
            await asyncio.sleep(delay)
