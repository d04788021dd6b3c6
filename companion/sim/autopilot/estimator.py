"""The mock autopilot's position estimate: drifting odometry, corrected by external vision.

PX4 reports (LOCAL_POSITION_NED, ODOMETRY, ATTITUDE, ...) its EKF's estimate, not the truth,
and its position controller flies that estimate to the setpoints. Indoors without GPS the
estimate drifts. :class:`SimEstimator` models that in the horizontal plane (PX4 local NED:
x north, y east, yaw from north towards east):

* the *raw* estimate is the true pose through an optional
  :class:`~companion.sim.odometry.OdometryDriftModel` (scale error, heading drift, noise);
  height, roll and pitch stay true (range finder and IMU keep them). The drift starts when
  the vehicle first arms (on the ground at rest, EKF2's zero-velocity updates hold it), so
  the frame the companion starts in is the true one;
* external vision (VISION_POSITION_ESTIMATE / ODOMETRY from the companion) is fused as EKF2
  does it with a delayed horizon: the sample is compared with the estimate *at its
  timestamp* (a short history is kept), and a fraction ``vision_gain`` of the difference is
  applied as a rigid correction to the whole estimate trajectory, so later samples see the
  corrected past and repeated corrections converge instead of piling up. Like EKF2, a sample
  not newer than the last fused one is ignored;
* setpoints arrive in the estimate's frame; :meth:`to_true` carries them into the true frame
  (what the airframe does when the controller flies the estimate to the setpoint).

Without a drift model and without vision the estimate is the truth.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import replace

import numpy as np

from companion.sim.autopilot.vehicle import _R_ENU_NED, _R_FRD_FLU, Target, VehicleState
from companion.sim.odometry import OdometryDriftModel
from semmap.frames import Transform, make_transform, rotation_from_rpy, wrap_angle_rad

#: Seconds of estimate history kept for delayed vision fusion.
HISTORY_S = 2.0


def T_map_body_of(state: VehicleState) -> Transform:  # noqa: N802 - frame names
    """(4, 4) pose of the FLU body in the map frame (ENU) of a NED/FRD ``state``."""
    R = _R_ENU_NED @ rotation_from_rpy(state.roll_rad, state.pitch_rad, state.yaw_rad) @ _R_FRD_FLU
    return make_transform(R, _R_ENU_NED @ np.asarray(state.position_ned_m, dtype=np.float64))


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle_rad(float(a[2] + b[2]))])


def _inverse(a: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle_rad(float(-a[2]))])


class SimEstimator:
    """Estimated horizontal pose of the mock vehicle (see the module docstring).

    ``drift``: the odometry drift (None = exact odometry). ``vision_gain``: fraction of a
    vision sample's innovation applied (0 = vision is recorded, not fused)."""

    def __init__(self, drift: OdometryDriftModel | None = None, vision_gain: float = 0.5) -> None:
        if not 0.0 <= vision_gain <= 1.0:
            raise ValueError(f"vision_gain must be in [0, 1] (got {vision_gain})")
        self.drift = drift
        self.vision_gain = float(vision_gain)
        #: Rigid correction from the raw (drifting) estimate to the reported one.
        self._correction = np.zeros(3)
        self._raw = np.zeros(3)
        self._est = np.zeros(3)
        self._true = np.zeros(3)
        self._stamps: deque[float] = deque()
        self._history: deque[np.ndarray] = deque()
        self._last_vision_s = -math.inf
        self.vision_fused = 0
        self._started = False
        self._drifting = False

    @property
    def active(self) -> bool:
        """True when the estimate can differ from the truth (drift or fused vision)."""
        return self.drift is not None or self.vision_fused > 0

    def update(self, state: VehicleState, armed: bool = True) -> VehicleState:
        """The estimated state for the true ``state`` (call once per physics tick);
        ``armed``: the drift starts at the first armed update."""
        n, e, _d = state.position_ned_m
        true = np.array([n, e, state.yaw_rad])
        self._drifting = self._drifting or armed
        drifting = self.drift is not None and self._drifting
        raw = self.drift.update(state.stamp_s, true) if drifting else true.copy()  # type: ignore[union-attr]
        self._true, self._raw, self._started = true, raw, True
        self._est = _compose(self._correction, raw)
        self._stamps.append(state.stamp_s)
        self._history.append(self._est.copy())
        while self._stamps and self._stamps[0] < state.stamp_s - HISTORY_S:
            self._stamps.popleft()
            self._history.popleft()
        return self.estimated(state)

    @property
    def raw_pose_ned(self) -> tuple[float, float, float]:
        """(north_m, east_m, yaw_rad) of the drifting odometry alone (no vision correction)."""
        return float(self._raw[0]), float(self._raw[1]), float(self._raw[2])

    def estimated(self, state: VehicleState) -> VehicleState:
        """``state`` (true) as the estimator reports it at the latest :meth:`update`."""
        if not self._started or not self.active:
            return state
        dyaw = wrap_angle_rad(float(self._est[2] - self._true[2]))
        scale = 1.0 + (self.drift.scale_error if self.drift is not None else 0.0)
        # The gyro's uncorrected bias is what drifts the heading: the reported rate has it too.
        bias = math.radians(self.drift.heading_drift_deg_s) if self.drift is not None and self._drifting else 0.0
        c, s = math.cos(dyaw), math.sin(dyaw)
        vn, ve, vd = state.velocity_ned_m_s
        return replace(
            state,
            position_ned_m=(float(self._est[0]), float(self._est[1]), state.position_ned_m[2]),
            velocity_ned_m_s=(scale * (c * vn - s * ve), scale * (s * vn + c * ve), vd),
            yaw_rad=float(self._est[2]),
            yaw_rate_rad_s=state.yaw_rate_rad_s + bias,
        )

    def fuse_vision(self, stamp_s: float, north_m: float, east_m: float, yaw_rad: float) -> bool:
        """Fuse one external-vision pose taken at ``stamp_s`` (the vehicle clock). Returns
        False when it is ignored: not newer than the last fused sample, no history yet, or
        a zero gain."""
        if stamp_s <= self._last_vision_s or not self._stamps or self.vision_gain <= 0.0:
            return False
        self._last_vision_s = stamp_s
        if self._stamps[0] <= stamp_s <= self._stamps[-1] + 0.5:
            k = min(bisect.bisect_left(self._stamps, stamp_s), len(self._stamps) - 1)
        else:  # not on our clock: no delay compensation
            k = len(self._stamps) - 1
        then = self._history[k]
        g = self.vision_gain
        dyaw = g * wrap_angle_rad(float(yaw_rad - then[2]))
        target_xy = then[:2] + g * (np.array([north_m, east_m]) - then[:2])
        # The rigid correction D: rotate by dyaw about the estimate at the sample's time and
        # move that point to target_xy. Applied to the past (history) and the future.
        c, s = math.cos(dyaw), math.sin(dyaw)
        rot_then = np.array([c * then[0] - s * then[1], s * then[0] + c * then[1]])
        D = np.array([target_xy[0] - rot_then[0], target_xy[1] - rot_then[1], dyaw])
        self._correction = _compose(D, self._correction)
        self._history = deque(_compose(D, h) for h in self._history)
        self._est = _compose(D, self._est)
        self.vision_fused += 1
        return True

    def shift(self, north_m: float, east_m: float) -> None:
        """Move the estimate from now on by (north, east) against the truth (dead reckoning's
        unseen drift); the recorded past stays as it was."""
        D = np.array([north_m, east_m, 0.0])
        self._correction = _compose(D, self._correction)
        self._est = _compose(D, self._est)

    def to_true(self, target: Target) -> Target:
        """A setpoint in the estimate's frame carried into the true frame."""
        if not self.active:
            return target
        T = _compose(self._true, _inverse(self._est))  # true <- estimate
        c, s = math.cos(T[2]), math.sin(T[2])
        pos = target.position_ned_m
        if pos is not None and math.isfinite(pos[0]) and math.isfinite(pos[1]):
            pos = (T[0] + c * pos[0] - s * pos[1], T[1] + s * pos[0] + c * pos[1], pos[2])
        vel = target.velocity_ned_m_s
        if vel is not None and math.isfinite(vel[0]) and math.isfinite(vel[1]):
            vel = (c * vel[0] - s * vel[1], s * vel[0] + c * vel[1], vel[2])
        yaw = None if target.yaw_rad is None else wrap_angle_rad(float(target.yaw_rad + T[2]))
        return replace(target, position_ned_m=pos, velocity_ned_m_s=vel, yaw_rad=yaw)
