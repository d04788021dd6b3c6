"""A kinematic multicopter: what PX4's position controller makes the airframe do.

Not a dynamics model. The vehicle tracks a position and/or velocity target the way PX4's
multicopter position controller does from the outside: velocity towards the target limited by
horizontal and vertical speed limits, a stopping profile ``v = sqrt(2 a d)`` so it arrives
without overshoot, acceleration limits, a yaw-rate limit, and tilt (roll/pitch) derived from the
commanded horizontal acceleration so attitude telemetry looks plausible.

Frames: PX4 local NED (x north, y east, z down, metres, origin = home on the floor), yaw in
radians from north, clockwise. The floor is ``z = 0``; the vehicle cannot go below it.
:meth:`KinematicMulticopter.T_map_body` gives the pose in the project's map frame (ENU) with
a FLU body, via :mod:`semmap.frames`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.frames import Transform, make_transform, rotation_from_rpy, wrap_angle_rad

GRAVITY_M_S2 = 9.80665

#: Rotation taking NED axes to ENU axes (also FRD body to FLU body up to a sign flip).
_R_ENU_NED: NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_R_FRD_FLU: NDArray[np.float64] = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class VehicleLimits:
    """Speed, acceleration and yaw-rate limits (PX4 MPC_* parameter equivalents)."""

    max_speed_xy_m_s: float = 5.0  # MPC_XY_VEL_MAX
    max_speed_up_m_s: float = 3.0  # MPC_Z_VEL_MAX_UP
    max_speed_down_m_s: float = 1.5  # MPC_Z_VEL_MAX_DN
    max_accel_xy_m_s2: float = 3.0  # MPC_ACC_HOR
    max_accel_z_m_s2: float = 4.0  # MPC_ACC_UP_MAX
    max_yaw_rate_rad_s: float = math.radians(60.0)  # MPC_YAWRAUTO_MAX
    #: Proportional gain on the position error near the target (1/s).
    position_gain_1_s: float = 1.5
    #: Proportional gain on the yaw error (1/s).
    yaw_gain_1_s: float = 2.5


@dataclass(frozen=True)
class Target:
    """What the position controller tracks (PX4 ``trajectory_setpoint`` equivalent).

    Any of the fields may be None: position only = go there and stop; velocity only = fly at
    that velocity; both = track the position with the velocity as feed-forward. Yaw is held when
    both ``yaw_rad`` and ``yaw_rate_rad_s`` are None. ``speed_xy_m_s`` further limits the
    horizontal speed (mission cruise speed) and ``speed_up_m_s`` the climb rate.
    """

    position_ned_m: tuple[float, float, float] | None = None  # NaN = axis not controlled
    velocity_ned_m_s: tuple[float, float, float] | None = None
    yaw_rad: float | None = None
    yaw_rate_rad_s: float | None = None
    speed_xy_m_s: float | None = None
    #: Further limit on the climb rate (takeoff speed, MPC_TKO_SPEED); None = the vehicle limit.
    speed_up_m_s: float | None = None
    #: Horizontal acceleration per m/s of velocity error (1/s, PX4's MPC_XY_VEL_P_ACC) for a
    #: target without acceleration feed-forward (offboard setpoints): the velocity trails the
    #: commanded one with time constant 1/gain. None (the auto modes' smooth trajectories): the
    #: velocity follows at once, within the acceleration limit.
    velocity_gain_1_s: float | None = None


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of the kinematic state (NED, metres, seconds, radians)."""

    stamp_s: float  # the simulation clock (seconds since the model started)
    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    yaw_rate_rad_s: float
    on_ground: bool


def _limit_norm(v: NDArray[np.float64], max_norm: float) -> NDArray[np.float64]:
    n = float(np.linalg.norm(v))
    if n > max_norm > 0.0:
        return v * (max_norm / n)
    return v


def _approach_speed(distance_m: float, v_max: float, a_max: float, gain: float) -> float:
    """Speed towards a target ``distance_m`` away that lets the vehicle stop on it."""
    return min(v_max, math.sqrt(2.0 * a_max * distance_m) * 0.9, gain * distance_m)


class KinematicMulticopter:
    """The kinematic vehicle. Call :meth:`step` at a fixed rate (e.g. 100 Hz).

    ``motors_on`` is set by the autopilot when armed; with motors off the vehicle rests on the
    floor (or falls to it, if disarmed in the air).
    """

    def __init__(
        self,
        limits: VehicleLimits | None = None,
        position_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        yaw_rad: float = 0.0,
    ) -> None:
        self.limits = limits or VehicleLimits()
        self.motors_on = False
        self._t_s = 0.0
        self._p = np.array(position_ned_m, dtype=np.float64)  # (3,) NED m
        self._p[2] = min(self._p[2], 0.0)
        self._v = np.zeros(3)  # (3,) NED m/s
        self._a = np.zeros(3)  # (3,) NED m/s^2, last commanded
        self._yaw = wrap_angle_rad(yaw_rad)
        self._yaw_rate = 0.0
        self._roll = 0.0
        self._pitch = 0.0
        self._target = Target(position_ned_m=tuple(self._p), yaw_rad=self._yaw)  # type: ignore[arg-type]
        #: (3,) NED m added to the target position: the controller's imperfect tracking.
        self.target_offset_ned_m: NDArray[np.float64] = np.zeros(3)

    # --- inputs --------------------------------------------------------------------------

    @property
    def target(self) -> Target:
        return self._target

    def set_target(self, target: Target) -> None:
        """Replace the controller's target (takes effect at the next :meth:`step`)."""
        self._target = target

    def hold_here(self) -> None:
        """Target the current position and heading (stop and hover, or stay on the floor)."""
        p = self._p.copy()
        self._target = Target(position_ned_m=(float(p[0]), float(p[1]), float(p[2])),
                              yaw_rad=self._yaw)

    # --- outputs -------------------------------------------------------------------------

    @property
    def stamp_s(self) -> float:
        return self._t_s

    @property
    def position_ned_m(self) -> tuple[float, float, float]:
        return (float(self._p[0]), float(self._p[1]), float(self._p[2]))

    @property
    def velocity_ned_m_s(self) -> tuple[float, float, float]:
        return (float(self._v[0]), float(self._v[1]), float(self._v[2]))

    @property
    def yaw_rad(self) -> float:
        return self._yaw

    @property
    def on_ground(self) -> bool:
        """True when resting on the floor (not climbing away from it)."""
        return self._p[2] >= -0.02 and self._v[2] >= -0.05

    def state(self) -> VehicleState:
        """The current state as an immutable snapshot."""
        return VehicleState(
            stamp_s=self._t_s,
            position_ned_m=self.position_ned_m,
            velocity_ned_m_s=self.velocity_ned_m_s,
            roll_rad=self._roll,
            pitch_rad=self._pitch,
            yaw_rad=self._yaw,
            yaw_rate_rad_s=self._yaw_rate,
            on_ground=self.on_ground,
        )

    def R_ned_frd(self) -> NDArray[np.float64]:  # noqa: N802 - frame names
        """(3, 3) attitude: rotation taking FRD body vectors to NED."""
        return rotation_from_rpy(self._roll, self._pitch, self._yaw)

    def T_map_body(self) -> Transform:  # noqa: N802 - frame names
        """(4, 4) pose of the FLU body in the map frame (ENU, origin = local NED origin)."""
        R = _R_ENU_NED @ self.R_ned_frd() @ _R_FRD_FLU
        return make_transform(R, _R_ENU_NED @ self._p)

    # --- simulation ----------------------------------------------------------------------

    def step(self, dt_s: float, clock_s: float | None = None) -> None:
        """Advance the model by ``dt_s`` seconds; ``clock_s``: the clock reading the new
        state is stamped with (default: the previous one plus ``dt_s``). A caller that caps
        ``dt_s`` after a stall passes its clock so the stamps stay on it."""
        if dt_s <= 0.0:
            return
        self._t_s = self._t_s + dt_s if clock_s is None else float(clock_s)
        lim = self.limits
        if not self.motors_on:
            self._step_unpowered(dt_s)
            return
        tgt = self._target
        v_des = self._desired_velocity(tgt)
        # Acceleration towards the desired velocity, limited per axis group.
        a = (v_des - self._v) / max(dt_s, 1e-3)
        if tgt.velocity_gain_1_s is not None:
            a[:2] = (v_des[:2] - self._v[:2]) * min(tgt.velocity_gain_1_s, 1.0 / max(dt_s, 1e-3))
        a_xy = _limit_norm(a[:2], lim.max_accel_xy_m_s2)
        a_z = float(np.clip(a[2], -lim.max_accel_z_m_s2, lim.max_accel_z_m_s2))
        self._a = np.array([a_xy[0], a_xy[1], a_z])
        self._v = self._v + self._a * dt_s
        self._p = self._p + self._v * dt_s
        if self._p[2] > 0.0:  # the floor
            self._p[2] = 0.0
            self._v[2] = min(self._v[2], 0.0)
            if self._v[2] >= 0.0:
                self._v[:2] *= 0.0  # resting on the floor: no sliding
        self._step_yaw(tgt, dt_s)
        self._update_tilt(dt_s)

    def _desired_velocity(self, tgt: Target) -> NDArray[np.float64]:
        lim = self.limits
        v_xy_max = lim.max_speed_xy_m_s
        if tgt.speed_xy_m_s is not None and tgt.speed_xy_m_s > 0.0:
            v_xy_max = min(v_xy_max, tgt.speed_xy_m_s)
        v_up_max = lim.max_speed_up_m_s
        if tgt.speed_up_m_s is not None and tgt.speed_up_m_s > 0.0:
            v_up_max = min(v_up_max, tgt.speed_up_m_s)
        v = np.zeros(3)
        if tgt.velocity_ned_m_s is not None:
            v = np.nan_to_num(np.array(tgt.velocity_ned_m_s, dtype=np.float64))
        if tgt.position_ned_m is not None:
            # NaN components leave that axis to the velocity (PX4 trajectory_setpoint style).
            err = np.array(tgt.position_ned_m, dtype=np.float64) + self.target_offset_ned_m - self._p
            d_xy = float(np.linalg.norm(err[:2]))
            if math.isfinite(d_xy) and d_xy > 1e-6:
                s = _approach_speed(d_xy, v_xy_max, lim.max_accel_xy_m_s2, lim.position_gain_1_s)
                v[:2] = v[:2] + err[:2] / d_xy * s
            d_z = abs(float(err[2]))
            if math.isfinite(d_z) and d_z > 1e-6:
                vz_max = lim.max_speed_down_m_s if err[2] > 0 else v_up_max
                s = _approach_speed(d_z, vz_max, lim.max_accel_z_m_s2, lim.position_gain_1_s)
                v[2] = v[2] + math.copysign(s, float(err[2]))
        v[:2] = _limit_norm(v[:2], v_xy_max)
        v[2] = float(np.clip(v[2], -v_up_max, lim.max_speed_down_m_s))
        return v

    def _step_yaw(self, tgt: Target, dt_s: float) -> None:
        lim = self.limits
        if tgt.yaw_rad is not None and math.isfinite(tgt.yaw_rad):
            err = wrap_angle_rad(tgt.yaw_rad - self._yaw)
            rate = lim.yaw_gain_1_s * err
            # Do not step past the target within one tick.
            rate = max(-abs(err) / dt_s, min(abs(err) / dt_s, rate))
        elif tgt.yaw_rate_rad_s is not None and math.isfinite(tgt.yaw_rate_rad_s):
            rate = tgt.yaw_rate_rad_s
        else:
            rate = 0.0
        if self.on_ground:
            rate = 0.0
        rate = max(-lim.max_yaw_rate_rad_s, min(lim.max_yaw_rate_rad_s, rate))
        self._yaw_rate = rate
        self._yaw = wrap_angle_rad(self._yaw + rate * dt_s)

    def _update_tilt(self, dt_s: float) -> None:
        # Tilt that produces the horizontal acceleration, in the heading frame, low-passed
        # (attitude loop time constant ~0.1 s).
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        a_fwd = c * self._a[0] + s * self._a[1]
        a_right = -s * self._a[0] + c * self._a[1]
        pitch_cmd = -math.atan2(a_fwd, GRAVITY_M_S2)
        roll_cmd = math.atan2(a_right, GRAVITY_M_S2)
        alpha = min(1.0, dt_s / 0.1)
        self._pitch += alpha * (pitch_cmd - self._pitch)
        self._roll += alpha * (roll_cmd - self._roll)
        if self.on_ground:
            self._roll = self._pitch = 0.0

    def _step_unpowered(self, dt_s: float) -> None:
        self._yaw_rate = 0.0
        self._roll = self._pitch = 0.0
        if self._p[2] < 0.0:  # falling
            self._v[2] += GRAVITY_M_S2 * dt_s
            self._p = self._p + self._v * dt_s
        if self._p[2] >= 0.0:
            self._p[2] = 0.0
            self._v[:] = 0.0
        self._a[:] = 0.0
