"""Poses for camera frames that arrive without one: the autopilot's pose at the frame's time.

A real depth camera (the RealSense) delivers images, not poses. The map needs each frame's
``T_map_camera``, so the service looks the vehicle's pose up in the autopilot's telemetry at
the frame's capture time, as a ROS node would look a transform up in tf at the image stamp:

* :class:`TelemetryPoseRecorder` (service process) turns each ATTITUDE from the autopilot,
  with the latest LOCAL_POSITION_NED moved on by its velocity to the attitude's time, into
  one map-frame body pose stamped with the message's ``time_boot_ms`` on this machine's clock
  (``time.monotonic``, the clock the camera stamps frames with; :class:`BootClock`). Beside
  it, a dead-reckoned *odometry* pose: the attitude's yaw rate and the body-frame velocity
  integrated. The position estimate fuses the external vision the companion sends (SLAM
  mode), so its increments carry the companion's own corrections back to it; the velocity
  and yaw rate do not (PX4 fuses a vision position into its position states; the body-frame
  velocity and the gyro rate are what the flow sensor and the IMU measured). Both are
  appended to
* :class:`SharedPoseHistory`, a ring buffer in shared memory (picklable into the ``spawn``ed
  perception process, where the camera is read);
* :class:`TelemetryPosedSource` wraps the camera: a frame without a pose gets the pose
  interpolated (position linearly, attitude by slerp, :class:`PoseTrack`) between the two
  telemetry samples around its stamp. When the newest sample is still older than the frame
  it waits up to ``wait_s`` for the next (telemetry streams at 30-50 Hz, so about one
  period); a frame no sample brackets within ``max_gap_s`` keeps no pose and is counted in
  :attr:`TelemetryPosedSource.unposed_frames` (perception skips and counts it too). The
  odometry pose is interpolated the same way into :attr:`semmap.types.Frame.T_odom_body`.
  Frames that already carry a pose (a recording with ground truth, the simulated camera in
  ``sim.camera_pose: autopilot``) pass unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation, Slerp

from companion.mavlink.state import MapFrame
from companion.shared_record import SharedRecord
from companion.sources.base import FrameSource, WrappedSource
from semmap.frames import (
    Transform,
    make_transform,
    map_pose_from_ned,
    ned_to_enu,
    rotation_from_rpy,
    rpy_from_rotation,
    wrap_angle_rad,
)
from semmap.slam.pose2d import from_matrix4
from semmap.types import Frame

log = logging.getLogger(__name__)

#: Telemetry samples kept (about 5 s at 50 Hz: longer than any camera latency).
HISTORY_SAMPLES = 256
#: Values per sample: stamp, x, y, z, quaternion x, y, z, w, odometry x, y, yaw (NaN: none).
_ROW = 11


class PoseTrack:
    """Poses at stamps, interpolated between them: position linearly, rotation by slerp.

    ``stamps_s`` (N,) in any order; ``poses`` N (4, 4) transforms. :meth:`at` gives None
    outside the track's time span or across a gap longer than ``max_gap_s``."""

    def __init__(self, stamps_s: NDArray[np.float64], poses: list[NDArray[np.float64]] | NDArray[np.float64],
                 max_gap_s: float) -> None:
        T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        self._init(np.asarray(stamps_s, dtype=np.float64), T[:, :3, 3],
                   Rotation.from_matrix(T[:, :3, :3]) if len(T) else None, max_gap_s)

    @classmethod
    def from_quaternions(cls, stamps_s: NDArray[np.float64], xyz_m: NDArray[np.float64],
                         quat_xyzw: NDArray[np.float64], max_gap_s: float) -> PoseTrack:
        """A track from positions (N, 3) and unit quaternions (N, 4, scipy's x, y, z, w order)."""
        track = cls.__new__(cls)
        track._init(np.asarray(stamps_s, dtype=np.float64), np.asarray(xyz_m, dtype=np.float64),
                    Rotation.from_quat(quat_xyzw) if len(quat_xyzw) else None, max_gap_s)
        return track

    def _init(self, t: NDArray[np.float64], xyz: NDArray[np.float64], rot: Rotation | None,
              max_gap_s: float) -> None:
        order = np.argsort(t, kind="stable")
        self.t = t[order]
        self.xyz = xyz.reshape(-1, 3)[order]
        self.rot = rot[order] if rot is not None else None
        self.max_gap_s = max_gap_s
        self._slerp = Slerp(self.t, self.rot) if len(self.t) >= 2 and np.all(np.diff(self.t) > 0) else None

    def at(self, t: float) -> NDArray[np.float64] | None:
        """The (4, 4) pose at ``t``, or None (outside the span, or across a long gap)."""
        if self.rot is None:
            return None
        k = int(np.searchsorted(self.t, t))
        if k < len(self.t) and abs(self.t[k] - t) < 1e-9:
            return make_transform(self.rot[k].as_matrix(), self.xyz[k])
        if k == 0 or k == len(self.t) or self._slerp is None:
            return None
        t0, t1 = self.t[k - 1], self.t[k]
        if t1 - t0 > self.max_gap_s:
            return None
        w = (t - t0) / (t1 - t0)
        xyz = (1 - w) * self.xyz[k - 1] + w * self.xyz[k]
        return make_transform(self._slerp([t]).as_matrix()[0], xyz)


class SharedPoseHistory:
    """The vehicle's recent map-frame body poses in shared memory: appended by the service
    (:class:`TelemetryPoseRecorder`), read where the camera is (:class:`TelemetryPosedSource`).
    Stamps must increase; a sample not newer than the last one is dropped."""

    def __init__(self, capacity: int = HISTORY_SAMPLES) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be at least 2 (got {capacity})")
        self.capacity = capacity
        # [samples ever written, rows...]: one writer (the service), readers never block it.
        self._record = SharedRecord(1 + capacity * _ROW)

    def __len__(self) -> int:
        return min(int(self._record.writer_view()[0]), self.capacity)

    def push(self, stamp_s: float, T_map_body: Transform,  # noqa: N803 - frame names
             odometry_xy_yaw: tuple[float, float, float] | None = None) -> bool:
        """Append one pose (4, 4) at ``stamp_s``, and the odometry pose (x_m, y_m, yaw_rad in
        the odometry frame, ENU) when there is one; False when it is not newer than the last
        or not finite. Only the process that owns the history (the service) may push."""
        T = np.asarray(T_map_body, dtype=np.float64)
        if T.shape != (4, 4) or not (math.isfinite(stamp_s) and np.all(np.isfinite(T))):
            return False
        odo = (math.nan,) * 3 if odometry_xy_yaw is None else tuple(float(v) for v in odometry_xy_yaw)
        if len(odo) != 3:
            return False
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        row = [float(stamp_s), *(float(v) for v in T[:3, 3]), *(float(v) for v in q), *odo]
        mine = self._record.writer_view()
        n = int(mine[0])
        if n and mine[1 + ((n - 1) % self.capacity) * _ROW] >= stamp_s:
            return False
        self._record.write_segments(((0, [n + 1]), (1 + (n % self.capacity) * _ROW, row)))
        return True

    def latest_stamp_s(self) -> float | None:
        """The newest sample's stamp (None when empty or unreadable just now)."""
        rows = self._rows_oldest_first()
        return None if len(rows) == 0 else float(rows[-1, 0])

    def _rows_oldest_first(self) -> NDArray[np.float64]:
        flat = self._record.read()
        if flat is None:  # the writer is mid-write for longer than a reader waits: no samples now
            return np.empty((0, _ROW))
        n = int(flat[0])
        rows = flat[1:].reshape(self.capacity, _ROW)
        if n > self.capacity:
            start = n % self.capacity
            rows = np.concatenate([rows[start:], rows[:start]])
        return rows[:min(n, self.capacity)]

    def track(self, max_gap_s: float) -> PoseTrack:
        """The samples held now, oldest first, as a :class:`PoseTrack`."""
        rows = self._rows_oldest_first()
        return PoseTrack.from_quaternions(rows[:, 0], rows[:, 1:4], rows[:, 4:8], max_gap_s)

    def pose_at(self, stamp_s: float, max_gap_s: float) -> Transform | None:
        """``track(max_gap_s).at(stamp_s)`` from the two samples around ``stamp_s`` only (a
        frame's lookup: a 256-sample track costs 1.5 ms to build, these two a fraction)."""
        near = self._around(stamp_s)
        return PoseTrack.from_quaternions(near[:, 0], near[:, 1:4], near[:, 4:8], max_gap_s).at(stamp_s)

    def odometry_at(self, stamp_s: float, max_gap_s: float) -> NDArray[np.float64] | None:
        """The odometry pose (3,) x_m, y_m, yaw_rad at ``stamp_s``, interpolated between the
        two samples around it as :class:`PoseTrack` does (position linearly, yaw the short
        way); None outside the samples, across a gap longer than ``max_gap_s``, or where the
        samples carry none."""
        near = self._around(stamp_s)
        near = near[np.all(np.isfinite(near[:, 8:11]), axis=1)]  # samples that carry one
        if len(near) == 0:
            return None
        odo = near[:, 8:11]
        xyz = np.column_stack([odo[:, :2], np.zeros(len(odo))])
        T = PoseTrack.from_quaternions(near[:, 0], xyz, Rotation.from_euler("z", odo[:, 2:3]).as_quat(),
                                       max_gap_s).at(stamp_s)
        return None if T is None else from_matrix4(T)

    def _around(self, stamp_s: float) -> NDArray[np.float64]:
        """The (up to two) rows around ``stamp_s``, oldest first."""
        rows = self._rows_oldest_first()
        k = int(np.searchsorted(rows[:, 0], stamp_s))
        return rows[max(0, k - 1):k + 1]


class BootClock:
    """Maps the autopilot's ``time_boot_ms`` onto this machine's clock.

    A message's arrival time is its send time plus a latency that varies (serial buffering,
    the event loop busy for a few tens of milliseconds): stamped on arrival, a pose taken
    while turning lands a tick late. The offset ``arrival - boot`` is smallest for the
    messages that waited least, so the estimate is its running minimum, allowed to rise by
    ``drift_s_per_s`` so it follows a slower clock (crystals: 100 ppm; the telemetry recorder
    allows 1.5 %, as a lockstep simulation runs about 1 % slow). A boot time that goes back by more than ``reboot_s`` (the autopilot rebooted)
    starts afresh. ``remote_to_local``: a better mapping when it has one (TIMESYNC round
    trips, :class:`~companion.mavlink.timesync.AutopilotClock`), used instead."""

    def __init__(self, drift_s_per_s: float = 1e-4, reboot_s: float = 1.0,
                 remote_to_local: Callable[[float], float | None] | None = None) -> None:
        self.drift_s_per_s = drift_s_per_s
        self.reboot_s = reboot_s
        self.remote_to_local = remote_to_local
        self._offset_s: float | None = None
        self._at_s = 0.0
        self._last_boot_s = -math.inf

    def to_local(self, boot_s: float, arrival_s: float) -> float:
        """The local time of ``boot_s`` (autopilot seconds), given the message arrived at
        ``arrival_s`` (local seconds); updates the offset estimate."""
        if boot_s < self._last_boot_s - self.reboot_s:
            self._offset_s = None
        self._last_boot_s = boot_s
        off = arrival_s - boot_s
        if self._offset_s is None or off <= self._offset_s:
            self._offset_s = off
        else:
            self._offset_s = min(off, self._offset_s + self.drift_s_per_s * max(0.0, arrival_s - self._at_s))
        self._at_s = arrival_s
        if self.remote_to_local is not None:
            local = self.remote_to_local(boot_s)
            if local is not None:
                return local
        return boot_s + self._offset_s


#: How fast the telemetry recorder's arrival-based clock mapping may follow a slower autopilot
#: clock before TIMESYNC round trips give it the rate (or when the autopilot answers none).
FALLBACK_DRIFT_S_PER_S = 0.015


class TelemetryPoseRecorder:
    """Feeds a :class:`SharedPoseHistory` from the autopilot's telemetry (a link listener:
    ``link.add_listener(recorder.handle, TelemetryPoseRecorder.MESSAGES)``).

    Each ATTITUDE makes one sample: that attitude with the latest LOCAL_POSITION_NED moved on
    by its velocity to the attitude's time, when that position is no more than
    ``max_position_age_s`` older. Stamps are the messages' ``time_boot_ms`` mapped onto
    ``clock`` (``time.monotonic``, the clock the camera stamps frames with) by a
    :class:`BootClock`. Only the autopilot's messages count (``target_system``/``target_component``).

    The sample's odometry pose is dead-reckoned from one sample to the next: the yaw by the
    ATTITUDE's ``yawspeed``, the position by the LOCAL_POSITION_NED velocity taken into the
    body frame (with the attitude's yaw) and out again with the odometry's yaw, midpoint
    rule. It starts at the first sample's pose. The interval integrated over is capped at
    ``max_position_age_s``: across a longer telemetry gap the odometry misses the motion
    of the gap (the SLAM's scan match takes it up) rather than extrapolating a stale velocity."""

    MESSAGES = ("ATTITUDE", "LOCAL_POSITION_NED")

    def __init__(self, history: SharedPoseHistory, target_system: int = 1,
                 target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1, max_position_age_s: float = 0.2,
                 clock: Callable[[], float] = time.monotonic,
                 remote_to_local: Callable[[float], float | None] | None = None,
                 map_frame: Callable[[], MapFrame | None] | None = None) -> None:
        self.history = history
        self.target_system = target_system
        self.target_component = target_component
        self.max_position_age_s = max_position_age_s
        self.clock = clock
        self.boot_clock = BootClock(drift_s_per_s=FALLBACK_DRIFT_S_PER_S, remote_to_local=remote_to_local)
        #: The map frame (heights above home) from the vehicle's state; no pose without one.
        #: None: PX4's local frame as it is (a recording or a test with the origin on the floor).
        self.map_frame = map_frame
        self._pos: tuple[float, float, float, float, float, float, float] | None = None  # t, xyz, vxyz
        #: Dead-reckoned odometry (x_m, y_m, yaw_rad; ENU) at ``_odo_t``.
        self._odo: NDArray[np.float64] | None = None
        self._odo_t = 0.0
        self.samples = 0

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != self.target_component:
            return
        mtype = msg.get_type()
        if mtype not in self.MESSAGES:
            return
        t_msg = self.boot_clock.to_local(msg.time_boot_ms * 1e-3, self.clock())
        if mtype == "LOCAL_POSITION_NED":
            vals = (float(msg.x), float(msg.y), float(msg.z), float(msg.vx), float(msg.vy), float(msg.vz))
            if all(math.isfinite(v) for v in vals):
                self._pos = (t_msg, *vals)
            return
        frame = self.map_frame() if self.map_frame is not None else MapFrame(0.0)
        if self._pos is None or frame is None:
            return
        rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
        t, x, y, z, vx, vy, vz = self._pos
        dt = t_msg - t
        if not all(math.isfinite(v) for v in rpy) or abs(dt) > self.max_position_age_s:
            return
        T = map_pose_from_ned((x + vx * dt, y + vy * dt, z + vz * dt - frame.floor_down_m), rpy)
        yaw_rate = float(msg.yawspeed)
        ve, vn, _ = ned_to_enu(vx, vy, vz)
        # A yaw rate about down (NED) is the negated rate about up (ENU).
        odo = self._dead_reckon(t_msg, T, (ve, vn), -yaw_rate if math.isfinite(yaw_rate) else 0.0)
        if self.history.push(t_msg, T, odo):
            self.samples += 1

    def _dead_reckon(self, t_s: float, T_map_body: Transform, velocity_enu_m_s: tuple[float, float],  # noqa: N803
                     yaw_rate_enu_rad_s: float) -> tuple[float, float, float]:
        """The odometry pose at ``t_s`` (see the class docstring)."""
        pose_map = from_matrix4(T_map_body)
        yaw_map = float(pose_map[2])
        if self._odo is None:
            self._odo = pose_map
            self._odo_t = t_s
        if t_s > self._odo_t:
            dt = min(t_s - self._odo_t, self.max_position_age_s)
            # Body-frame velocity (what the flow sensor measured), then out with the odometry's yaw.
            c, s = math.cos(yaw_map), math.sin(yaw_map)
            ve, vn = velocity_enu_m_s
            v_fwd, v_left = c * ve + s * vn, -s * ve + c * vn
            mid = float(self._odo[2]) + 0.5 * yaw_rate_enu_rad_s * dt
            cm, sm = math.cos(mid), math.sin(mid)
            self._odo[0] += (cm * v_fwd - sm * v_left) * dt
            self._odo[1] += (sm * v_fwd + cm * v_left) * dt
            self._odo[2] = wrap_angle_rad(float(self._odo[2]) + yaw_rate_enu_rad_s * dt)
            self._odo_t = t_s
        return float(self._odo[0]), float(self._odo[1]), float(self._odo[2])


class TelemetryPosedSource(WrappedSource):
    """``inner``'s frames, those without a pose posed from ``history`` at their stamp (see
    the module docstring). ``T_body_camera``: the camera's mounting (4, 4). ``wait_s``: how
    long a frame newer than the newest sample waits for the next one; ``max_gap_s``: the
    longest interval between two samples that is interpolated across."""

    def __init__(self, inner: FrameSource, history: SharedPoseHistory, T_body_camera: Transform,  # noqa: N803
                 *, wait_s: float = 0.1, max_gap_s: float = 0.25, poll_s: float = 0.002) -> None:
        super().__init__(inner)
        self.history = history
        self.T_body_camera = np.asarray(T_body_camera, dtype=np.float64)
        self.wait_s = wait_s
        self.max_gap_s = max_gap_s
        self.poll_s = poll_s
        #: Frames left without a pose (no telemetry around their stamp).
        self.unposed_frames = 0
        self.posed_frames = 0

    def pose_at(self, stamp_s: float) -> Transform | None:
        """The body pose at ``stamp_s`` (waits up to ``wait_s`` for a sample after it)."""
        deadline = time.monotonic() + self.wait_s
        while True:
            last = self.history.latest_stamp_s()
            if (last is not None and last >= stamp_s) or time.monotonic() >= deadline:
                break
            time.sleep(self.poll_s)
        return self.history.pose_at(stamp_s, self.max_gap_s)

    def read(self) -> Frame | None:
        frame = self.inner.read()
        if frame is None or frame.T_map_camera is not None:
            return frame
        T_map_body = self.pose_at(frame.stamp_s)
        if T_map_body is None:
            self.unposed_frames += 1
            if self.unposed_frames == 1 or self.unposed_frames % 100 == 0:
                last = self.history.latest_stamp_s()
                log.warning("frame %d at %.3f s has no telemetry pose (newest sample %s; %d frames so far)",
                            frame.index, frame.stamp_s, "none" if last is None else f"at {last:.3f} s",
                            self.unposed_frames)
            return frame
        self.posed_frames += 1
        odo = self.history.odometry_at(frame.stamp_s, self.max_gap_s)
        T_odom_body = None
        if odo is not None:
            # Height, roll and pitch are the estimate's (range finder, IMU: no drift, no vision).
            roll, pitch, _ = rpy_from_rotation(T_map_body[:3, :3])
            T_odom_body = make_transform(rotation_from_rpy(roll, pitch, float(odo[2])),
                                         np.array([odo[0], odo[1], T_map_body[2, 3]]))
        return replace(frame, T_map_camera=T_map_body @ self.T_body_camera, T_odom_body=T_odom_body)
