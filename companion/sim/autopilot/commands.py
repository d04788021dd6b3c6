"""The mock autopilot's MAVLink command protocol (COMMAND_LONG / COMMAND_INT -> COMMAND_ACK).

Every command is answered at once (inside the receive callback, so well under PX4's typical
ack latency) with the result PX4 would give. Clients re-send a command when an ack is lost
(MAVSDK increments ``confirmation``); a re-send (confirmation > 0, or any repeat of a
COMMAND_INT) of the same command with the same parameters from the same sender within
:data:`DUPLICATE_WINDOW_S` is re-acknowledged with the earlier result and *not* executed again,
so a re-sent "takeoff" cannot restart a takeoff.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

from companion import px4
from companion.px4 import FlightMode
from companion.sim.autopilot.guided import DEFAULT_ORBIT_SPEED_M_S, Orbit

if TYPE_CHECKING:
    from companion.sim.autopilot.mock import MockAutopilot

#: Modes PX4 refuses to arm in (``mode_req_prevent_arming``).
PREVENTS_ARMING = frozenset({FlightMode.LAND, FlightMode.RTL, FlightMode.PRECLAND, FlightMode.ORBIT,
                             FlightMode.FOLLOW_TARGET})
#: MAV_CMD_INJECT_FAILURE units the mock simulates (sensors whose health bit it clears).
FAILURE_UNITS = frozenset({
    mavlink.FAILURE_UNIT_SENSOR_GYRO, mavlink.FAILURE_UNIT_SENSOR_ACCEL, mavlink.FAILURE_UNIT_SENSOR_MAG,
    mavlink.FAILURE_UNIT_SENSOR_BARO, mavlink.FAILURE_UNIT_SENSOR_GPS,
})

log = logging.getLogger(__name__)

DUPLICATE_WINDOW_S = 1.5
#: COMMAND_INT's "no value" for x/y (MAVLink: INT32_MAX).
INT32_MAX = 2**31 - 1

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
DENIED = mavlink.MAV_RESULT_DENIED
TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
CRITICAL = mavlink.MAV_SEVERITY_CRITICAL
FAILED = mavlink.MAV_RESULT_FAILED

#: What PX4 says when its health and arming checks refuse to arm (not ready, mode not armable).
HEALTH_DENIAL = "Arming denied: Resolve system health failures first"

#: Modes PX4 lets you arm in (without RC; POSCTL etc. hold position in the mock).
ARMABLE_MODES = frozenset({
    FlightMode.HOLD, FlightMode.POSCTL, FlightMode.ALTCTL, FlightMode.MANUAL,
    FlightMode.STABILIZED, FlightMode.OFFBOARD, FlightMode.MISSION, FlightMode.TAKEOFF,
    FlightMode.READY,
})


@dataclass(frozen=True)
class CommandRecord:
    """A command as received and what the mock answered (None = not answered)."""

    stamp_s: float
    command: int
    params: tuple[float, ...]  # param1..param7 (COMMAND_INT x/y as degE7 integers)
    source: tuple[int, int]  # (system id, component id)
    result: int | None
    duplicate: bool


def result_name(result: int) -> str:
    return str(mavlink.enums["MAV_RESULT"][result].name)


def command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(command)
    return str(entry.name) if entry is not None else f"MAV_CMD {command}"


class CommandHandler:
    """Executes commands against a :class:`MockAutopilot` and acknowledges them."""

    def __init__(self, ap: MockAutopilot) -> None:
        self._ap = ap
        self.history: deque[CommandRecord] = deque(maxlen=500)
        self._recent: dict[tuple[int, int, int], tuple[tuple[float, ...], float, int]] = {}

    def received(self, command: int) -> list[CommandRecord]:
        """Records of ``command`` received so far (oldest first)."""
        return [r for r in self.history if r.command == command]

    def handle(self, msg: Any, now_s: float) -> None:
        cmd = int(msg.command)
        fields = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z) \
            if msg.get_type() == "COMMAND_INT" else (
            msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        params: tuple[float, ...] = tuple(float(p) for p in fields)
        src = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        tc = int(getattr(msg, "target_component", 0))
        if tc not in (0, px4.MAV_COMP_ID_AUTOPILOT1):
            return  # for another component (camera, gimbal) of this system
        key = (src[0], src[1], cmd)
        prev = self._recent.get(key)
        # COMMAND_LONG marks re-sends with confirmation > 0; a fresh attempt (confirmation 0,
        # e.g. arming again after a denial) is executed. COMMAND_INT has no such field.
        resend = msg.get_type() == "COMMAND_INT" or int(msg.confirmation) > 0
        if resend and prev is not None and now_s - prev[1] < DUPLICATE_WINDOW_S and \
                _same(prev[0], params):
            self.history.append(CommandRecord(now_s, cmd, params, src, prev[2], True))
            self._ack(cmd, prev[2], src)
            return
        faults = self._ap.faults
        if cmd in faults.ignore_commands:
            log.info("%s ignored (fault injection)", command_name(cmd))
            self.history.append(CommandRecord(now_s, cmd, params, src, None, False))
            return
        if cmd in faults.reject_commands:
            result = DENIED
            log.info("%s denied (fault injection)", command_name(cmd))
        else:
            result = self._execute(cmd, params, msg.get_type() == "COMMAND_INT")
        self._recent[key] = (params, now_s, result)
        self.history.append(CommandRecord(now_s, cmd, params, src, result, False))
        log.debug("%s -> %s", command_name(cmd), result_name(result))
        self._ack(cmd, result, src)

    def _ack(self, cmd: int, result: int, src: tuple[int, int]) -> None:
        ap = self._ap
        ap.send(ap._mav.command_ack_encode(cmd, result, 0, 0, src[0], src[1]))

    # --- the commands --------------------------------------------------------------------

    def _execute(self, cmd: int, p: tuple[float, ...], is_int: bool) -> int:
        handler = _HANDLERS.get(cmd)
        if handler is None:
            log.info("%s not supported", command_name(cmd))
            return UNSUPPORTED
        return handler(self, p, is_int)

    def _arm_disarm(self, p: tuple[float, ...], is_int: bool) -> int:
        ap = self._ap
        if p[0] >= 0.5:
            if ap.armed:
                return ACCEPTED
            if ap.faults.prearm_fail:
                ap.announce(CRITICAL, "Arming denied: pre-arm checks failed")
                return DENIED
            if not ap.ready or not ap.position_ok:
                ap.announce(CRITICAL, HEALTH_DENIAL)
                return TEMPORARILY_REJECTED
            if ap.behaviour.mode_after_disarm and (ap.mode in PREVENTS_ARMING or (
                    ap.mode is FlightMode.OFFBOARD and not ap.offboard_available())):
                ap.announce(CRITICAL, HEALTH_DENIAL)
                return TEMPORARILY_REJECTED
            if ap.mode not in ARMABLE_MODES:
                ap.announce(CRITICAL, f"Arming denied: not armable in {ap.mode.name.title()}")
                return DENIED
            if ap.mode is FlightMode.MISSION and ap.navigator.mission_count == 0:
                ap.announce(CRITICAL, "Arming denied: no valid mission")
                return DENIED
            if ap.mode is FlightMode.OFFBOARD and not ap.offboard_available():
                return DENIED
            ap.arm()
            return ACCEPTED
        if not ap.armed:
            return ACCEPTED
        if ap.in_air and p[1] != px4.PX4_FORCE_DISARM_MAGIC:
            ap.announce(CRITICAL, "Disarming denied: not landed")
            return DENIED
        ap.disarm()
        return ACCEPTED

    def _takeoff(self, p: tuple[float, ...], is_int: bool) -> int:
        ap = self._ap
        if not ap.armed:
            ap.announce(CRITICAL, "Takeoff denied: disarmed")
            return DENIED
        alt_rel = None
        if math.isfinite(p[6]):
            alt_rel = p[6] - ap.home.alt_m  # param7 is AMSL
            if alt_rel <= 0.0:
                return DENIED
        ap.set_mode(FlightMode.TAKEOFF, takeoff_alt_m=alt_rel)
        return ACCEPTED

    def _land(self, p: tuple[float, ...], is_int: bool) -> int:
        self._ap.set_mode(FlightMode.LAND)
        return ACCEPTED

    def _rtl(self, p: tuple[float, ...], is_int: bool) -> int:
        ap = self._ap
        if not ap.armed or not ap.in_air:
            return DENIED
        ap.set_mode(FlightMode.RTL)
        return ACCEPTED

    def _set_mode(self, p: tuple[float, ...], is_int: bool) -> int:
        mode = px4.mode_from_set_mode_params(p[0], p[1], p[2])
        if mode is None:
            log.warning("DO_SET_MODE with unknown mode %s", p[:3])
            return DENIED
        return self._switch(mode)

    def _switch(self, mode: FlightMode) -> int:
        ap = self._ap
        if mode is ap.mode:
            return ACCEPTED
        # PX4 accepts any mode while disarmed and checks it when arming.
        disarmed_choice = ap.behaviour.mode_after_disarm and not ap.armed
        if mode is FlightMode.OFFBOARD and not ap.offboard_available() and not disarmed_choice:
            ap.announce(CRITICAL, "Switching to Offboard is currently not available")
            return TEMPORARILY_REJECTED
        if mode is FlightMode.OFFBOARD and ap.mode is FlightMode.TAKEOFF and \
                ap.behaviour.offboard_during_takeoff_dropped:
            log.info("Offboard requested during take-off: acknowledged, take-off continues")
            return ACCEPTED
        if mode is FlightMode.MISSION and ap.navigator.mission_count == 0:
            ap.announce(CRITICAL, "Switching to Mission: no valid mission")
            return TEMPORARILY_REJECTED
        if mode in (FlightMode.RTL, FlightMode.LAND, FlightMode.TAKEOFF, FlightMode.FOLLOW_TARGET,
                    FlightMode.ORBIT) and not ap.armed:
            return TEMPORARILY_REJECTED
        if mode is FlightMode.ORBIT and ap.navigator.orbit is None:
            return TEMPORARILY_REJECTED  # an orbit starts with MAV_CMD_DO_ORBIT
        if mode in (FlightMode.PRECLAND, FlightMode.ACRO, FlightMode.RATTITUDE):
            return TEMPORARILY_REJECTED
        ap.set_mode(mode)
        return ACCEPTED

    def _mission_start(self, p: tuple[float, ...], is_int: bool) -> int:
        ap = self._ap
        first = int(p[0])
        if ap.navigator.mission_count == 0:
            return DENIED
        if 0 < first < ap.navigator.mission_count:
            ap.navigator.set_current(first)
        return self._switch(FlightMode.MISSION)

    def _set_mission_current(self, p: tuple[float, ...], is_int: bool) -> int:
        return ACCEPTED if self._ap.navigator.set_current(int(p[0])) else DENIED

    def _request_message(self, p: tuple[float, ...], is_int: bool) -> int:
        if int(p[0]) == mavlink.MAVLINK_MSG_ID_HOME_POSITION and not self._ap.ready:
            return FAILED  # PX4 has no home before its pre-flight checks pass
        return ACCEPTED if self._ap.send_message_by_id(int(p[0])) else UNSUPPORTED

    def _request_capabilities(self, p: tuple[float, ...], is_int: bool) -> int:
        self._ap.send_message_by_id(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        return ACCEPTED

    def _set_message_interval(self, p: tuple[float, ...], is_int: bool) -> int:
        return ACCEPTED if self._ap.set_stream_interval(int(p[0]), p[1]) else UNSUPPORTED

    def _change_speed(self, p: tuple[float, ...], is_int: bool) -> int:
        if p[1] <= 0:
            return DENIED
        self._ap.navigator.set_cruise_speed(p[1])
        return ACCEPTED

    def _reposition(self, p: tuple[float, ...], is_int: bool) -> int:
        ap = self._ap
        if not ap.armed or not ap.in_air:
            return DENIED
        lat = p[4] * 1e-7 if is_int else p[4]
        lon = p[5] * 1e-7 if is_int else p[5]
        n, e, d = ap.position_ned_m
        if math.isfinite(lat) and math.isfinite(lon) and (lat != 0 or lon != 0):
            n, e, _ = ap.home.to_ned(lat, lon, ap.home.alt_m)
        if math.isfinite(p[6]):
            d = ap.home.alt_m - p[6] + ap.height_error_m  # AMSL altitude, as the estimate has it
        if p[0] > 0:
            ap.navigator.set_cruise_speed(p[0])
        ap.set_mode(FlightMode.HOLD, hold_at_ned_m=(n, e, d))
        return ACCEPTED


    def _orbit(self, p: tuple[float, ...], is_int: bool) -> int:
        """MAV_CMD_DO_ORBIT: radius, tangential speed (> 0 clockwise), yaw behaviour, centre
        lat/lon (NaN or INT32_MAX in COMMAND_INT: here) and altitude AMSL (NaN: current)."""
        ap = self._ap
        if not ap.armed or not ap.in_air:
            return TEMPORARILY_REJECTED
        n, e, d = ap.position_ned_m
        lat, lon = (_deg_of_int(p[4]), _deg_of_int(p[5])) if is_int else (p[4], p[5])
        prev = ap.navigator.orbit if ap.mode is FlightMode.ORBIT else None
        center = (n, e) if prev is None else prev.center_ne_m
        if math.isfinite(lat) and math.isfinite(lon):
            center = ap.home.to_ned(lat, lon, ap.home.alt_m)[:2]
        radius = p[0] if math.isfinite(p[0]) else (prev.radius_m if prev else math.hypot(n - center[0], e - center[1]))
        if not 0.0 < abs(radius) <= ap.params.get("MC_ORBIT_RAD_MAX"):
            return DENIED
        speed = p[1] if math.isfinite(p[1]) else (prev.speed_m_s if prev else DEFAULT_ORBIT_SPEED_M_S)
        yaw = int(p[2]) if math.isfinite(p[2]) else mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TO_CIRCLE_CENTER
        down = ap.home.alt_m - p[6] if math.isfinite(p[6]) else d
        # A negative radius orbits counter-clockwise (as a negative speed does).
        ap.navigator.orbit = Orbit(center, abs(radius), speed if radius > 0 else -speed, down, yaw)
        ap.set_mode(FlightMode.ORBIT)
        return ACCEPTED

    def _inject_failure(self, p: tuple[float, ...], is_int: bool) -> int:
        """MAV_CMD_INJECT_FAILURE (unit, type, instance), only with SYS_FAILURE_EN set."""
        ap = self._ap
        if int(ap.params.get("SYS_FAILURE_EN")) != 1:
            ap.announce(CRITICAL, "Failure injection disabled")
            return DENIED
        unit, kind, instance = int(p[0]), int(p[1]), int(p[2])
        if unit not in FAILURE_UNITS:
            return UNSUPPORTED
        if kind == mavlink.FAILURE_TYPE_OK:
            ap.failures.pop((unit, instance), None)
        else:
            ap.failures[(unit, instance)] = kind
        log.info("failure injected: unit %d instance %d type %d", unit, instance, kind)
        return ACCEPTED


def _deg_of_int(value: float) -> float:
    """Degrees of a COMMAND_INT x/y (degE7); INT32_MAX means "not given" (NaN)."""
    return math.nan if value == INT32_MAX else value * 1e-7


def _same(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return all((x == y) or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b, strict=True))


_HANDLERS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: CommandHandler._arm_disarm,
    mavlink.MAV_CMD_NAV_TAKEOFF: CommandHandler._takeoff,
    mavlink.MAV_CMD_NAV_LAND: CommandHandler._land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: CommandHandler._rtl,
    mavlink.MAV_CMD_DO_SET_MODE: CommandHandler._set_mode,
    mavlink.MAV_CMD_MISSION_START: CommandHandler._mission_start,
    mavlink.MAV_CMD_DO_SET_MISSION_CURRENT: CommandHandler._set_mission_current,
    mavlink.MAV_CMD_REQUEST_MESSAGE: CommandHandler._request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: CommandHandler._request_capabilities,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: CommandHandler._set_message_interval,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: CommandHandler._change_speed,
    mavlink.MAV_CMD_DO_REPOSITION: CommandHandler._reposition,
    mavlink.MAV_CMD_DO_ORBIT: CommandHandler._orbit,
    mavlink.MAV_CMD_INJECT_FAILURE: CommandHandler._inject_failure,
}
