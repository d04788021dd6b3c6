"""PX4's navigator in miniature: the automatic modes (takeoff, hold, land, RTL, mission).

Each tick the navigator turns the active auto mode into a :class:`~.vehicle.Target` for the
kinematic vehicle, and reports what happened (item reached, mode finished) through callbacks so
the MAVLink side can send ``MISSION_ITEM_REACHED``/``MISSION_CURRENT`` and switch modes the way
PX4 does: TAKEOFF ends in HOLD, a finished mission holds at its last waypoint, LAND and RTL end
on the floor where the autopilot disarms.

Mission items are read in their stored MAVLink form (``MISSION_ITEM_INT`` fields) and converted
to local NED around home with :class:`companion.geo.GeoOrigin`.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GeoOrigin
from companion.px4 import FlightMode
from companion.sim.autopilot.guided import FollowParams, FollowTarget, Orbit
from companion.sim.autopilot.mission_server import GLOBAL_FRAMES, MissionItem
from companion.sim.autopilot.params import ParamStore
from companion.sim.autopilot.vehicle import KinematicMulticopter, Target

log = logging.getLogger(__name__)

_NAN3 = (math.nan, math.nan, math.nan)
#: Mission commands whose item holds a position (PX4's ``item_contains_position``).
POSITION_COMMANDS = frozenset({
    mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_LOITER_UNLIM, mavlink.MAV_CMD_NAV_LOITER_TIME,
    mavlink.MAV_CMD_NAV_LOITER_TURNS, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
})


class MissionState(enum.IntEnum):
    """``MISSION_STATE`` as reported in ``MISSION_CURRENT``."""

    NO_MISSION = mavlink.MISSION_STATE_NO_MISSION
    NOT_STARTED = mavlink.MISSION_STATE_NOT_STARTED
    ACTIVE = mavlink.MISSION_STATE_ACTIVE
    PAUSED = mavlink.MISSION_STATE_PAUSED
    COMPLETE = mavlink.MISSION_STATE_COMPLETE


class _Phase(enum.Enum):
    IDLE = "idle"
    CLIMB = "climb"  # vertical climb before heading off (takeoff, RTL, mission from ground)
    GOTO = "goto"  # fly to a point at constant altitude
    WAIT = "wait"  # hold position until a time
    DESCEND = "descend"
    LAND = "land"
    DONE = "done"


@dataclass
class _Leg:
    """The navigator's current leg (one mission item or one stage of an auto mode)."""

    phase: _Phase
    target_ned_m: tuple[float, float, float]
    yaw_rad: float | None = None
    accept_radius_m: float = 0.5
    until_s: float = 0.0  # for WAIT
    hold_s: float = 0.0  # hold time after arriving (NAV_WAYPOINT param1)
    reported: bool = False  # MISSION_ITEM_REACHED already sent for this leg


class Navigator:
    """Auto-mode logic. ``set_mode(mode)`` is called when a mode ends by itself (e.g. takeoff
    done -> HOLD); ``item_reached(seq)`` and ``current_changed(seq)`` report mission progress.
    """

    def __init__(
        self,
        vehicle: KinematicMulticopter,
        params: ParamStore,
        home: GeoOrigin,
        set_mode: Callable[[FlightMode], None],
        item_reached: Callable[[int], None],
        current_changed: Callable[[int], None],
        *,
        null_island_items: bool = False,
        land_brake_accel_m_s2: float = 0.0,
    ) -> None:
        self._vehicle = vehicle
        #: Land engaged while moving lands where a brake at this rate stops (0: where engaged).
        self.land_brake_accel_m_s2 = land_brake_accel_m_s2
        #: PX4 flies an item's lat/lon 0/0 as given (True) instead of taking it as "here".
        self.null_island_items = null_island_items
        self._params = params
        self.home = home  # the local NED origin, for lat/lon conversions
        #: Home (where the vehicle last armed) in local NED: RTL target, relative altitudes.
        self.home_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._set_mode = set_mode
        self._item_reached = item_reached
        self._current_changed = current_changed
        self.mode: FlightMode | None = None
        self._legs: list[_Leg] = []
        self._mission: list[MissionItem] = []
        self.mission_seq = 0
        self.mission_state = MissionState.NO_MISSION
        self._jump_counts: dict[int, int] = {}
        self._speed_xy_m_s: float | None = None
        self.landed_by_navigator = False
        self._last_goto_ned_m: tuple[float, float, float] | None = None
        #: The orbit being flown in ORBIT mode (set by MAV_CMD_DO_ORBIT).
        self.orbit: Orbit | None = None
        #: The latest FOLLOW_TARGET (followed in FOLLOW_TARGET mode).
        self.follow_target: FollowTarget | None = None

    # --- mission storage -----------------------------------------------------------------

    def set_mission(self, items: list[MissionItem]) -> None:
        """A new mission was uploaded (or cleared): restart it from its current item."""
        self._mission = list(items)
        self._jump_counts.clear()
        start = next((i for i, it in enumerate(items) if it.current), 0)
        self.mission_seq = start if items else 0
        self.mission_state = MissionState.NOT_STARTED if items else MissionState.NO_MISSION
        if self.mode is FlightMode.MISSION:
            self._start_mission_item(self._now())
        self._current_changed(self.mission_seq)

    def set_cruise_speed(self, speed_xy_m_s: float) -> None:
        """Horizontal speed for missions and repositioning (DO_CHANGE_SPEED), m/s."""
        self._speed_xy_m_s = speed_xy_m_s

    @property
    def mission_count(self) -> int:
        return len(self._mission)

    def set_current(self, seq: int) -> bool:
        """Jump to mission item ``seq``; False if out of range."""
        if not 0 <= seq < len(self._mission):
            return False
        self.mission_seq = seq
        if self.mission_state is MissionState.COMPLETE:
            self.mission_state = MissionState.NOT_STARTED
        if self.mode is FlightMode.MISSION:
            self._start_mission_item(self._now())
        self._current_changed(seq)
        return True

    # --- mode entry ----------------------------------------------------------------------

    def _now(self) -> float:
        return self._vehicle.stamp_s

    def _pos(self) -> tuple[float, float, float]:
        return self._vehicle.position_ned_m

    def enter(self, mode: FlightMode, takeoff_alt_m: float | None = None,
              hold_at_ned_m: tuple[float, float, float] | None = None) -> None:
        """Start auto ``mode`` (non-auto modes leave the navigator idle)."""
        if self.mode is FlightMode.MISSION and mode is not FlightMode.MISSION:
            if self.mission_state is MissionState.ACTIVE:
                self.mission_state = MissionState.PAUSED
        self.mode = mode
        self.landed_by_navigator = False
        self._legs = []
        n, e, d = self._pos()
        yaw = self._vehicle.yaw_rad
        if mode is FlightMode.TAKEOFF:
            alt = takeoff_alt_m if takeoff_alt_m is not None else self._params.get("MIS_TAKEOFF_ALT")
            self._legs = [_Leg(_Phase.CLIMB, (n, e, -abs(alt)), yaw, accept_radius_m=0.1)]
        elif mode is FlightMode.HOLD:
            target = hold_at_ned_m if hold_at_ned_m is not None else self._brake_point()
            prev = self._vehicle.target.position_ned_m
            if hold_at_ned_m is None and prev is not None and math.isfinite(prev[2]) \
                    and abs(prev[2] - d) < 0.5:
                # Hold the altitude being flown to (e.g. the takeoff altitude), not the
                # altitude the vehicle happens to pass through.
                target = (target[0], target[1], prev[2])
            self._legs = [_Leg(_Phase.WAIT, target, yaw, until_s=math.inf)]
        elif mode is FlightMode.FOLLOW_TARGET:
            # Holds until a FOLLOW_TARGET arrives, then follows it (see tick).
            self._legs = [_Leg(_Phase.WAIT, (n, e, d), yaw, until_s=math.inf)]
        elif mode is FlightMode.LAND:
            if self.land_brake_accel_m_s2 > 0.0:
                n, e, _ = self._brake_point(self.land_brake_accel_m_s2)
            self._legs = [_Leg(_Phase.LAND, (n, e, math.nan), yaw)]
        elif mode is FlightMode.RTL:
            self._legs = self._rtl_legs()
        elif mode is FlightMode.MISSION:
            if self.mission_state in (MissionState.COMPLETE, MissionState.NO_MISSION):
                self.mission_seq = 0
                self._jump_counts.clear()
            self.mission_state = (MissionState.ACTIVE if self._mission
                                  else MissionState.NO_MISSION)
            self._start_mission_item(self._now())
        self._apply_leg()

    def _brake_point(self, accel_m_s2: float | None = None) -> tuple[float, float, float]:
        """Where the vehicle stops if it brakes now at ``accel_m_s2`` (default: the horizontal
        acceleration limit)."""
        (n, e, d), (vn, ve, _vd) = self._pos(), self._vehicle.velocity_ned_m_s
        a = self._vehicle.limits.max_accel_xy_m_s2 if accel_m_s2 is None else accel_m_s2
        speed = math.hypot(vn, ve)
        if speed < 1e-3:
            return (n, e, d)
        s = speed * speed / (2.0 * a)
        return (n + vn / speed * s, e + ve / speed * s, d)

    def _rtl_legs(self) -> list[_Leg]:
        n, e, d = self._pos()
        hn, he, hd = self.home_ned_m
        yaw = self._vehicle.yaw_rad
        ret_d = hd - self._params.get("RTL_RETURN_ALT")
        desc_d = hd - self._params.get("RTL_DESCEND_ALT")
        cruise_d = min(d, ret_d)
        legs = []
        if cruise_d < d - 0.05:
            legs.append(_Leg(_Phase.CLIMB, (n, e, cruise_d), yaw, accept_radius_m=0.2))
        legs.append(_Leg(_Phase.GOTO, (hn, he, cruise_d), None, accept_radius_m=0.3))
        if desc_d > cruise_d + 0.05:
            legs.append(_Leg(_Phase.DESCEND, (hn, he, desc_d), None, accept_radius_m=0.2))
        delay = self._params.get("RTL_LAND_DELAY")
        if delay > 0:
            legs.append(_Leg(_Phase.GOTO, (hn, he, max(cruise_d, desc_d)), None,
                             accept_radius_m=0.3, hold_s=delay))
        legs.append(_Leg(_Phase.LAND, (hn, he, math.nan), None))
        return legs

    # --- mission items -------------------------------------------------------------------

    def _item_ned(self, it: MissionItem) -> tuple[float, float, float]:
        """Local NED of an item; lat/lon 0/0 is "here" unless :attr:`null_island_items`."""
        n, e, d = self._pos()
        if it.frame not in GLOBAL_FRAMES:
            return (n, e, d)
        if it.frame in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT):
            alt_d = self.home.alt_m - it.z  # AMSL
        else:
            alt_d = self.home_ned_m[2] - it.z  # relative to home
        if it.x != 0 or it.y != 0 or self.null_island_items:
            tn, te, _ = self.home.to_ned(it.lat_deg, it.lon_deg, self.home.alt_m)
            return (tn, te, alt_d)
        return (n, e, alt_d)

    def first_waypoint_distance_m(self) -> float | None:
        """Horizontal distance from home to the mission's first item with a position (what
        PX4's feasibility check compares with ``MIS_DIST_1WP``); None without one."""
        for it in self._mission:
            if it.command in POSITION_COMMANDS and it.frame in GLOBAL_FRAMES:
                n, e, _ = (self.home.to_ned(it.lat_deg, it.lon_deg, self.home.alt_m)
                           if it.x != 0 or it.y != 0 or self.null_island_items else self._pos())
                return math.hypot(n - self.home_ned_m[0], e - self.home_ned_m[1])
        return None

    def _accept_radius(self, it: MissionItem) -> float:
        return it.param2 if it.param2 > 0 else self._params.get("NAV_ACC_RAD")

    def _start_mission_item(self, now_s: float) -> None:
        """Build the legs for the current item, skipping over non-navigation items."""
        self._legs = []
        guard = 0
        while self.mission_seq < len(self._mission) and guard < 1000:
            guard += 1
            it = self._mission[self.mission_seq]
            legs = self._legs_for_item(it, now_s)
            if legs is None:  # a DO/condition item, executed instantly
                self._item_done_instant(it)
                continue
            if self._vehicle.on_ground and legs[0].phase is not _Phase.CLIMB \
                    and it.command != mavlink.MAV_CMD_NAV_LAND:
                # PX4 takes off before flying a mission started on the ground.
                n, e, _ = self._pos()
                alt = max(self._params.get("MIS_TAKEOFF_ALT"), -legs[0].target_ned_m[2]
                          if math.isfinite(legs[0].target_ned_m[2]) else 0.0)
                legs.insert(0, _Leg(_Phase.CLIMB, (n, e, -alt), self._vehicle.yaw_rad,
                                    accept_radius_m=0.2))
            self._legs = legs
            self._current_changed(self.mission_seq)
            return
        if self.mission_seq >= len(self._mission) and self._mission:
            self._mission_complete()

    def _legs_for_item(self, it: MissionItem, now_s: float) -> list[_Leg] | None:
        c = it.command
        if c in (mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_LOITER_TIME,
                 mavlink.MAV_CMD_NAV_LOITER_UNLIM):
            tgt = self._item_ned(it)
            yaw = math.radians(it.param4) if c == mavlink.MAV_CMD_NAV_WAYPOINT and \
                math.isfinite(it.param4) else None
            hold = it.param1 if c in (mavlink.MAV_CMD_NAV_WAYPOINT,
                                      mavlink.MAV_CMD_NAV_LOITER_TIME) else math.inf
            return [_Leg(_Phase.GOTO, tgt, yaw, self._accept_radius(it), hold_s=max(0.0, hold))]
        if c == mavlink.MAV_CMD_NAV_TAKEOFF:
            # Straight up where the vehicle is; already higher = reached (PX4 does the same).
            tn, te, td = self._item_ned(it)
            n, e, d = self._pos()
            legs = [_Leg(_Phase.CLIMB, (n, e, min(td, d)), self._vehicle.yaw_rad, accept_radius_m=0.2)]
            if self.null_island_items and it.frame in GLOBAL_FRAMES:
                # Then on to the item's position, as PX4 does (0/0 included).
                legs.append(_Leg(_Phase.GOTO, (tn, te, min(td, d)), None, self._accept_radius(it)))
            return legs
        if c == mavlink.MAV_CMD_NAV_LAND:
            n, e, d = self._item_ned(it)
            cur_d = self._pos()[2]
            return [_Leg(_Phase.GOTO, (n, e, cur_d), None, self._accept_radius(it)),
                    _Leg(_Phase.LAND, (n, e, math.nan), None)]
        if c == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._rtl_legs()
        if c == mavlink.MAV_CMD_NAV_DELAY:
            return [_Leg(_Phase.WAIT, self._pos(), None, until_s=now_s + max(0.0, it.param1))]
        return None

    def _item_done_instant(self, it: MissionItem) -> None:
        c = it.command
        if c == mavlink.MAV_CMD_DO_CHANGE_SPEED and it.param2 > 0:
            self._speed_xy_m_s = it.param2
        elif c == mavlink.MAV_CMD_DO_JUMP:
            target, repeats = int(it.param1), int(it.param2)
            done = self._jump_counts.get(it.seq, 0)
            if 0 <= target < len(self._mission) and (repeats < 0 or done < repeats):
                self._jump_counts[it.seq] = done + 1
                self.mission_seq = target
                return
        elif c == mavlink.MAV_CMD_CONDITION_YAW and it.param4 == 0:
            n, e, d = self._pos()
            self._vehicle.set_target(Target(position_ned_m=(n, e, d),
                                            yaw_rad=math.radians(it.param1)))
        self.mission_seq += 1

    def _mission_complete(self) -> None:
        self.mission_seq = len(self._mission) - 1
        self.mission_state = MissionState.COMPLETE
        log.info("mission complete")
        n, e, d = self._pos()
        if self._vehicle.on_ground:
            self._legs = [_Leg(_Phase.DONE, (n, e, d), None)]
        else:
            # PX4 loiters at the last waypoint, not where the acceptance radius was entered.
            last = self._last_goto_ned_m
            hold = last if last is not None and all(math.isfinite(v) for v in last) else (n, e, d)
            self._legs = [_Leg(_Phase.WAIT, hold, self._vehicle.yaw_rad, until_s=math.inf)]

    # --- the tick ------------------------------------------------------------------------

    def _apply_leg(self) -> None:
        if not self._legs:
            return
        leg = self._legs[0]
        speed = self._speed_xy_m_s if self.mode is FlightMode.MISSION else None
        if leg.phase is _Phase.LAND:
            land_speed = self._params.get("MPC_LAND_SPEED")
            n, e, _ = leg.target_ned_m
            self._vehicle.set_target(Target(position_ned_m=(n, e, math.nan),
                                            velocity_ned_m_s=(0.0, 0.0, land_speed),
                                            yaw_rad=leg.yaw_rad, speed_xy_m_s=speed))
            return
        if leg.phase is _Phase.DONE:
            self._vehicle.hold_here()
            return
        # PX4 climbs at MPC_TKO_SPEED while taking off (takeoff mode, mission takeoff).
        climb = self._params.get("MPC_TKO_SPEED") if leg.phase is _Phase.CLIMB and (
            self.mode is FlightMode.TAKEOFF or self.mode is FlightMode.MISSION) else None
        yaw = leg.yaw_rad
        if yaw is None and leg.phase is _Phase.GOTO:
            n, e, _ = self._pos()
            dn, de = leg.target_ned_m[0] - n, leg.target_ned_m[1] - e
            yaw = math.atan2(de, dn) if math.hypot(dn, de) > 1.0 else None
        self._vehicle.set_target(Target(position_ned_m=leg.target_ned_m, yaw_rad=yaw,
                                        speed_xy_m_s=speed, speed_up_m_s=climb))

    def lower_hold(self, delta_m: float) -> bool:
        """Move a Hold's target ``delta_m`` down (true frame), as PX4's Hold does when its height
        estimate creeps up; False when not holding a point."""
        if self.mode is not FlightMode.HOLD or not self._legs or self._legs[0].phase is not _Phase.WAIT:
            return False
        leg = self._legs[0]
        n, e, d = leg.target_ned_m
        leg.target_ned_m = (n, e, d + delta_m)
        self._apply_leg()
        return True

    def tick(self, now_s: float) -> None:
        """Advance the active auto mode (call once per physics step, after the vehicle moved)."""
        if not self._vehicle.motors_on:
            return
        if self.mode is FlightMode.ORBIT and self.orbit is not None:
            self._vehicle.set_target(self.orbit.target(self._pos()))
            return
        if self.mode is FlightMode.FOLLOW_TARGET and self.follow_target is not None:
            p = self._params.get
            params = FollowParams(p("FLW_TGT_HT"), p("FLW_TGT_DST"), p("FLW_TGT_FA"), int(p("FLW_TGT_ALT_M")))
            self._vehicle.set_target(self.follow_target.setpoint(params, self.home_ned_m[2]))
            return
        if self.mode is None or not self.mode.is_auto or not self._legs:
            return
        leg = self._legs[0]
        n, e, d = self._pos()
        tn, te, td = leg.target_ned_m
        arrived = False
        if leg.phase in (_Phase.CLIMB, _Phase.DESCEND):
            arrived = abs(d - td) < leg.accept_radius_m
        elif leg.phase is _Phase.GOTO:
            arrived = (math.hypot(tn - n, te - e) < leg.accept_radius_m
                       and abs(td - d) < max(0.3, leg.accept_radius_m))
            if arrived and self.mode is FlightMode.MISSION and len(self._legs) == 1:
                # PX4 reports an item reached on arrival, before any hold time.
                self._item_reached(self.mission_seq)
                leg.reported = True
            if arrived and leg.hold_s > 0:
                leg.phase, leg.until_s = _Phase.WAIT, now_s + leg.hold_s
                arrived = False
        elif leg.phase is _Phase.WAIT:
            arrived = now_s >= leg.until_s
        elif leg.phase is _Phase.LAND:
            arrived = self._vehicle.on_ground
        if arrived:
            self._legs.pop(0)
            if leg.phase in (_Phase.GOTO, _Phase.WAIT):
                self._last_goto_ned_m = leg.target_ned_m
            if not self._legs:
                self._mode_leg_sequence_done(now_s, report_reached=not leg.reported)
        self._apply_leg()

    def _mode_leg_sequence_done(self, now_s: float, report_reached: bool) -> None:
        mode = self.mode
        if mode is FlightMode.TAKEOFF:
            self._set_mode(FlightMode.HOLD)
        elif mode in (FlightMode.LAND, FlightMode.RTL):
            self.landed_by_navigator = True
            n, e, d = self._pos()
            self._legs = [_Leg(_Phase.DONE, (n, e, d), None)]
        elif mode is FlightMode.MISSION:
            if report_reached:
                self._item_reached(self.mission_seq)
            if self._vehicle.on_ground and self._mission[self.mission_seq].command in (
                    mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH):
                self.landed_by_navigator = True
            self.mission_seq += 1
            if self.mission_seq >= len(self._mission):
                self._mission_complete()
            else:
                self._start_mission_item(now_s)
