"""Orbit (``MAV_CMD_DO_ORBIT``) and Follow Target (``FOLLOW_TARGET``) as PX4's flight tasks fly them.

Each turns the vehicle's current position into a :class:`~.vehicle.Target` for the kinematic
vehicle every physics tick. Frames: the mock's true local NED (floor at z = 0), yaw from north,
clockwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.sim.autopilot.vehicle import Target

#: PX4's default orbit speed when DO_ORBIT gives none (m/s, MC_ORBIT flight task).
DEFAULT_ORBIT_SPEED_M_S = 1.0


@dataclass
class Orbit:
    """A circle around ``center_ne_m`` at ``down_m``; ``speed_m_s`` > 0 flies clockwise seen
    from above (MAVLink's convention); ``yaw_behaviour`` is an ``ORBIT_YAW_BEHAVIOUR``."""

    center_ne_m: tuple[float, float]
    radius_m: float
    speed_m_s: float
    down_m: float
    yaw_behaviour: int = mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TO_CIRCLE_CENTER

    def target(self, position_ned_m: tuple[float, float, float]) -> Target:
        """Where to fly from ``position_ned_m``: the nearest point of the circle, moving on
        along it at the orbit speed."""
        n, e, _d = position_ned_m
        cn, ce = self.center_ne_m
        angle = math.atan2(e - ce, n - cn) if math.hypot(n - cn, e - ce) > 1e-6 else 0.0
        c, s = math.cos(angle), math.sin(angle)
        point = (cn + self.radius_m * c, ce + self.radius_m * s, self.down_m)
        velocity = (-self.speed_m_s * s, self.speed_m_s * c, 0.0)
        yaw: float | None = None
        if self.yaw_behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TO_CIRCLE_CENTER:
            yaw = math.atan2(ce - point[1], cn - point[0])
        elif self.yaw_behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TANGENT_TO_CIRCLE:
            yaw = math.atan2(velocity[1], velocity[0])
        return Target(position_ned_m=point, velocity_ned_m_s=velocity, yaw_rad=yaw,
                      speed_xy_m_s=abs(self.speed_m_s) + 1.0)


@dataclass(frozen=True)
class FollowParams:
    """PX4's ``FLW_TGT_*`` parameters: height above home (m), distance (m), angle from the
    target's heading (deg, 180 = behind), altitude mode (0 = constant height above home,
    2 = the target's altitude plus the height)."""

    height_m: float
    distance_m: float
    angle_deg: float
    altitude_mode: int


@dataclass
class FollowTarget:
    """The latest FOLLOW_TARGET, in local NED; ``heading_rad`` is kept from the last time
    the target moved."""

    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]
    stamp_s: float
    heading_rad: float = 0.0

    def update(self, position_ned_m: tuple[float, float, float],
               velocity_ned_m_s: tuple[float, float, float], stamp_s: float) -> None:
        self.position_ned_m, self.velocity_ned_m_s, self.stamp_s = position_ned_m, velocity_ned_m_s, stamp_s
        vn, ve, _ = velocity_ned_m_s
        if math.isfinite(vn) and math.isfinite(ve) and math.hypot(vn, ve) > 0.5:
            self.heading_rad = math.atan2(ve, vn)

    def setpoint(self, params: FollowParams, home_down_m: float) -> Target:
        """Where the follower flies: ``distance_m`` from the target at ``angle_deg`` from its
        heading, facing it."""
        tn, te, td = self.position_ned_m
        angle = self.heading_rad + math.radians(params.angle_deg)
        n = tn + params.distance_m * math.cos(angle)
        e = te + params.distance_m * math.sin(angle)
        base = td if params.altitude_mode == 2 and math.isfinite(td) else home_down_m
        vn, ve, _ = self.velocity_ned_m_s
        velocity = (vn, ve, 0.0) if math.isfinite(vn) and math.isfinite(ve) else None
        return Target(position_ned_m=(n, e, base - params.height_m), velocity_ned_m_s=velocity,
                      yaw_rad=math.atan2(te - e, tn - n))
