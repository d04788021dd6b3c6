"""The take-off and engage sequence the mission runner flies before its first leg.

Arm once PX4 is ready (:meth:`TakeoffSteps.arm_when_ready`), let PX4 take off, engage OFFBOARD
only in the air clear of the floor with the first setpoint at the vehicle
(:meth:`TakeoffSteps.engage_here`), climb on the spot to the flight altitude
(:meth:`TakeoffSteps.climb_to`) and turn once on the spot (:meth:`TakeoffSteps.survey`) so the
map has seen all round. Heights are above the floor the vehicle took off from.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CommandError, MissionError
from companion.mavlink.commands import CommandDeniedError, CommandTemporarilyRejectedError
from companion.mavlink.failsafe import OffboardState, PositionSetpoint
from companion.mavlink.state import VehicleState
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.service.mission_legs import FEED_PERIOD_S, map_frame_of, position_enu
from planner.config import PlannerConfig
from semmap.frames import wrap_angle_rad

log = logging.getLogger(__name__)

#: The take-off survey's yaw setpoint leads the measured heading by this much (degrees) ...
SURVEY_CARROT_DEG = 30.0
#: ... and the survey ends this close to its full turn (degrees) or after twice its time at
#: the planner's yaw rate plus this margin (seconds).
SURVEY_DONE_DEG = 5.0
SURVEY_SETTLE_S = 2.0
#: OFFBOARD is engaged only this high above the floor, at least (and at least half the
#: take-off altitude): PX4's take-off aims at its home, whose height can be off by tens of
#: centimetres, so the last part of the climb to the flight altitude is flown in OFFBOARD.
MIN_ENGAGE_HEIGHT_M = 0.3
#: The climb from the engage height to the flight altitude (m/s), and when it is done (m).
CLIMB_SPEED_M_S = 0.5
CLIMB_DONE_M = 0.1
#: OFFBOARD is requested only this much above the engage height (metres, by the lower of the
#: estimate and the range sensor), so a Hold sinking through the heartbeat's lag before PX4
#: reports the switch still engages above it.
ENGAGE_MARGIN_M = 0.1
#: A Hold that sank below that is asked to climb again at most this often (seconds), and the
#: engage gives up when the height is not back within ENGAGE_READY_TIMEOUT_S.
ENGAGE_CLIMB_RETRY_S = 3.0
ENGAGE_READY_TIMEOUT_S = 10.0
#: OFFBOARD is engaged only with the first setpoint this close to the vehicle (metres).
ENGAGE_MAX_OFFSET_M = 0.5
#: Pause between refused arming attempts (PX4 re-runs its checks at about 1 Hz).
ARM_RETRY_S = 2.0


def min_engage_height_m(altitude_m: float) -> float:
    """How high above the floor the vehicle must be before OFFBOARD is engaged."""
    return max(MIN_ENGAGE_HEIGHT_M, 0.5 * altitude_m)


def engage_clearance_m(altitude_m: float) -> float:
    """How high above the floor the vehicle must be when OFFBOARD is requested: the engage
    height plus :data:`ENGAGE_MARGIN_M`, but no higher than the take-off altitude."""
    need = min_engage_height_m(altitude_m)
    return max(need, min(need + ENGAGE_MARGIN_M, altitude_m))


def took_off(state: VehicleState, altitude_m: float) -> bool:
    """PX4's take-off to ``altitude_m`` has finished: in the air, out of TAKEOFF (PX4 ends
    it in Hold, and drops an OFFBOARD request made before), and clear of the floor by
    :func:`min_engage_height_m`, by the estimate and by a downward range sensor where there
    is one."""
    height = state.clearance_below_m()
    return (state.in_air and state.flight_mode is not FlightMode.TAKEOFF and height is not None
            and height >= min_engage_height_m(altitude_m))


def clear_to_engage(state: VehicleState, altitude_m: float) -> bool:
    """OFFBOARD may be requested now: :func:`took_off`, and by the lower of the estimate and
    the range sensor at least :func:`engage_clearance_m` above the floor. PX4's Hold flies
    its height estimate, which can creep away from the floor during the setpoint warm-up."""
    height = state.clearance_below_m()
    return took_off(state, altitude_m) and height is not None and height >= engage_clearance_m(altitude_m)


class SurveyTurn:
    """The take-off survey's yaw setpoints: a turn on the spot by ``total_rad``, one way.

    Fed the measured heading (NED, radians) each step, :meth:`next_yaw` gives the yaw setpoint:
    a carrot :data:`SURVEY_CARROT_DEG` ahead of the heading, never past the end of the turn,
    so the vehicle turns at whatever rate its autopilot allows (PX4's yaw-rate limit may be
    below the planner's) and a setpoint racing more than half a turn ahead can never send it
    back the short way; None once the turn is within :data:`SURVEY_DONE_DEG` of complete.
    Shared by :meth:`MissionRunner.survey` and the lock-step safety bench.
    """

    def __init__(self, yaw0_rad: float, total_rad: float, yaw_rate_rad_s: float) -> None:
        self.yaw0_rad = yaw0_rad
        self.total_rad = total_rad
        self.turned_rad = 0.0
        self._prev = yaw0_rad
        #: Seconds the turn may take: twice its time at ``yaw_rate_rad_s`` plus a margin.
        self.max_duration_s = 2.0 * total_rad / yaw_rate_rad_s + SURVEY_SETTLE_S

    def next_yaw(self, heading_rad: float | None) -> float | None:
        if heading_rad is not None:
            self.turned_rad += wrap_angle_rad(heading_rad - self._prev)
            self._prev = heading_rad
        left = self.total_rad - self.turned_rad
        if left <= math.radians(SURVEY_DONE_DEG):
            return None
        return wrap_angle_rad(self._prev + min(left, math.radians(SURVEY_CARROT_DEG)))

    @property
    def final_yaw_rad(self) -> float:
        """The heading the turn ends at (the setpoint to hold afterwards)."""
        return wrap_angle_rad(self.yaw0_rad + self.total_rad)



class TakeoffSteps:
    """The vehicle steps before and around a mission's legs, for :class:`MissionRunner`
    (which provides ``vehicle`` and the planner config ``cfg``): take-off, engage, climb,
    survey, and holds."""

    vehicle: Vehicle
    cfg: PlannerConfig

    async def take_off(self, altitude_m: float, timeout_s: float = 30.0) -> None:
        """Arm once PX4 is ready, take off to ``altitude_m`` above PX4's home (set where it
        armed), wait until the take-off has finished, engage OFFBOARD holding where the vehicle
        is, and climb (or descend) on the spot to ``altitude_m`` above the floor."""
        v = self.vehicle
        if not v.snapshot().in_air:
            await self.arm_when_ready()
            # PX4 takes the altitude above home as AMSL; home streams only on change, so the
            # copy we hold can predate the one PX4 set at arming: climb from where it stands.
            state = v.snapshot()
            ground_above_home_m = 0.0
            if state.global_position is not None and state.home is not None:
                ground_above_home_m = state.global_position.altitude_amsl_m - state.home.altitude_amsl_m
            commanded_s = time.monotonic()
            await v.commands.takeoff(altitude_m + ground_above_home_m)
            # PX4 reports its mode in a 1 Hz heartbeat: until one sent after the command, the
            # mode shown is the one before the take-off, not its end.
            await v.state.wait_for(lambda s: took_off(s, altitude_m) and s.heartbeat_age_s is not None
                                   and time.monotonic() - s.heartbeat_age_s > commanded_s, timeout_s,
                                   f"the take-off to {altitude_m:.2f} m to finish")
        await self.engage_here(altitude_m)
        await self.climb_to(altitude_m)
        await self.survey(altitude_m)

    async def arm_when_ready(self) -> None:
        """Wait for PX4's readiness (pre-arm checks, home, local position), leave a mode PX4
        will not arm in (it keeps OFFBOARD or LAND after landing), then arm, retrying a
        refusal a bounded number of times."""
        v = self.vehicle
        await v.state.wait_for(lambda s: s.ready_to_arm, v.cfg.ready_timeout_s,
                               "the autopilot to be ready to arm (pre-arm checks, home, local position)")
        await self.make_armable()
        for attempt in range(v.cfg.arm_retries + 1):
            try:
                await v.commands.arm()
                break
            except (CommandDeniedError, CommandTemporarilyRejectedError) as exc:
                if attempt == v.cfg.arm_retries:
                    raise MissionError(f"arming refused {attempt + 1} times: {exc}") from exc
                log.warning("arming refused (%s); retrying in %.0f s", exc, ARM_RETRY_S)
                await asyncio.sleep(ARM_RETRY_S)
                await self.make_armable()
        await v.state.wait_for(lambda s: s.armed, v.cfg.heartbeat_timeout_s, "the vehicle to report armed")

    async def make_armable(self) -> None:
        """Put a vehicle on the ground into Hold, the one mode it is armed in here: PX4 keeps
        OFFBOARD or Land after a landing, refuses Position and Altitude without RC, and
        armed in Mission flies its own uploaded mission."""
        v = self.vehicle
        state = v.snapshot()
        if state.in_air or state.armed or state.flight_mode is FlightMode.HOLD:
            return
        assert state.flight_mode is not None
        log.info("vehicle on the ground in %s: switching to HOLD so it can arm", state.flight_mode.name)
        await v.commands.set_mode(FlightMode.HOLD)
        await v.state.wait_for(lambda s: s.flight_mode is FlightMode.HOLD, v.cfg.heartbeat_timeout_s,
                               "the vehicle to report HOLD")

    async def survey(self, altitude_m: float, turn_deg: float | None = None) -> None:
        """Turn on the spot by ``turn_deg`` (default ``planner.takeoff_survey_deg``), holding
        position at ``altitude_m``, so the map has seen all round (:class:`SurveyTurn`)."""
        total = math.radians(self.cfg.takeoff_survey_deg if turn_deg is None else turn_deg)
        snap = self.vehicle.snapshot()
        xy = self._hold_xy()
        if total <= 0.0 or xy is None:
            return
        if snap.yaw_ned_rad is None:
            log.warning("survey skipped: no heading from the autopilot yet")
            return
        turn = SurveyTurn(snap.yaw_ned_rad, total, math.radians(self.cfg.max_yaw_rate_deg_s))
        target = map_frame_of(snap).to_ned(float(xy[0]), float(xy[1]), altitude_m)
        deadline = time.monotonic() + turn.max_duration_s
        log.info("survey: turning %.0f deg on the spot", math.degrees(total))
        while time.monotonic() < deadline:
            self._check_offboard()
            yaw = turn.next_yaw(self.vehicle.snapshot().yaw_ned_rad)
            if yaw is None:
                break
            self.vehicle.offboard.set_setpoint(PositionSetpoint(target, yaw_rad=yaw))
            await asyncio.sleep(FEED_PERIOD_S)
        else:
            log.warning("survey: turned %.0f of %.0f deg before its time ran out",
                        math.degrees(turn.turned_rad), math.degrees(total))
        self.vehicle.offboard.set_setpoint(PositionSetpoint(target, yaw_rad=turn.final_yaw_rad))

    async def engage_here(self, altitude_m: float) -> None:
        """Hold where the vehicle is and engage OFFBOARD; only in the air, clear of the floor
        (:func:`took_off`), with that hold near the vehicle, so OFFBOARD never starts on the
        ground or with a setpoint somewhere else."""
        xy, hold_z_m = self._hold_where_airborne(altitude_m)

        async def follow_climb() -> None:
            # PX4's Hold may still be climbing while the stream warms up (1 s, then up to a
            # heartbeat for the switch): the hold rises with the vehicle, never pulling it back
            # down towards the floor when OFFBOARD takes over. A Hold that sank below the
            # engage clearance is asked to climb back to the take-off altitude.
            top_m = hold_z_m
            climb_asked_s = -math.inf
            while True:
                snap = self.vehicle.snapshot()
                now = position_enu(snap)
                if now is not None and float(now[2]) > top_m:
                    top_m = float(now[2])
                    self.hold_at(xy, top_m)
                height = snap.clearance_below_m()
                # A climb asked for after the OFFBOARD request would switch PX4 back to Hold.
                if not switch_asked and height is not None and height < engage_clearance_m(altitude_m) \
                        and time.monotonic() - climb_asked_s >= ENGAGE_CLIMB_RETRY_S:
                    climb_asked_s = time.monotonic()
                    climbing.set()
                    try:
                        await self.climb_in_hold(snap, altitude_m)
                    finally:
                        climbing.clear()
                await asyncio.sleep(FEED_PERIOD_S)

        switch_asked = False
        # Set while a climb command (and its re-sends) is in flight: one landing after the
        # OFFBOARD request would put PX4 back into Hold.
        climbing = asyncio.Event()

        def ready(s: VehicleState) -> bool:
            nonlocal switch_asked
            switch_asked = switch_asked or (not climbing.is_set() and clear_to_engage(s, altitude_m))
            return switch_asked

        follower = asyncio.create_task(follow_climb())
        need_m = engage_clearance_m(altitude_m)
        try:
            await self.vehicle.offboard.engage(
                ready=ready, ready_timeout_s=ENGAGE_READY_TIMEOUT_S,
                ready_what=f"the vehicle to hold {need_m:.2f} m above the floor (estimate and range "
                           f"sensor) before OFFBOARD")
        finally:
            follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await follower

    def _hold_where_airborne(self, altitude_m: float) -> tuple[NDArray[np.float64], float]:
        """Hold where the vehicle is and return that hold (map frame xy, height above the floor
        in metres); a :class:`MissionError` unless the vehicle is airborne clear of the floor
        (:func:`took_off`) and the hold's setpoint lies near it."""
        state = self.vehicle.snapshot()
        pos = position_enu(state)
        if pos is None:
            raise MissionError("no vehicle position (or no floor height) to engage offboard from")
        if not state.in_air or not took_off(state, altitude_m):
            raise MissionError(f"not engaging offboard: the vehicle is not airborne clear of the floor "
                               f"({'in the air' if state.in_air else 'on the ground'}, "
                               f"{pos[2]:.2f} m above the floor, range below "
                               f"{'none' if state.range_down_m is None else f'{state.range_down_m:.2f} m'}, "
                               f"{min_engage_height_m(altitude_m):.2f} m needed)")
        xy = pos[:2].copy()
        self.hold_at(xy, float(pos[2]))
        sp = self.vehicle.offboard.status().setpoint
        assert sp is not None
        offset = math.dist(sp.position_ned_m, map_frame_of(state).to_ned(*pos))
        if offset > ENGAGE_MAX_OFFSET_M:
            raise MissionError(f"not engaging offboard: the first setpoint is {offset:.2f} m from the vehicle")
        return xy, float(pos[2])

    async def climb_in_hold(self, state: VehicleState, altitude_m: float) -> None:
        """Ask PX4's Hold to climb where it is (DO_REPOSITION to an altitude above the current
        one, position unchanged) until the lower of the estimate and the range sensor reads
        ``altitude_m``; a refusal is logged (the engage then times out naming the height)."""
        height = state.clearance_below_m()
        pos = state.global_position
        if height is None or pos is None:
            return
        up_m = altitude_m - height
        log.warning("%.2f m above the floor (estimate %s, range sensor %s) is below the %.2f m to engage "
                    "OFFBOARD: asking PX4's Hold to climb %.2f m", height,
                    "none" if state.height_above_floor_m is None else f"{state.height_above_floor_m:.2f} m",
                    "none" if state.range_down_m is None else f"{state.range_down_m:.2f} m",
                    engage_clearance_m(altitude_m), up_m)
        try:
            await self.vehicle.commands.sender.command_long(
                mavlink.MAV_CMD_DO_REPOSITION, -1.0, float(mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE), 0.0,
                math.nan, math.nan, math.nan, pos.altitude_amsl_m + up_m)
        except CommandError as exc:
            log.warning("PX4 refused the climb in Hold: %s", exc)

    async def climb_to(self, altitude_m: float, timeout_s: float = 20.0) -> None:
        """Climb (or descend) on the spot, in OFFBOARD, to ``altitude_m`` above the floor, the
        setpoint moving at :data:`CLIMB_SPEED_M_S` so the vehicle never lags it far."""
        pos = position_enu(self.vehicle.snapshot())
        xy = self._hold_xy()
        if pos is None or xy is None:
            raise MissionError("no vehicle position to climb from")
        z0 = float(pos[2])
        t0 = time.monotonic()
        while True:
            self._check_offboard()
            step = CLIMB_SPEED_M_S * (time.monotonic() - t0)
            # The last setpoint is the altitude itself (z0 plus the rest need not equal it exactly).
            ramp_done = step >= abs(altitude_m - z0)
            z_sp = altitude_m if ramp_done else z0 + math.copysign(step, altitude_m - z0)
            self.hold_at(xy, z_sp)
            now = position_enu(self.vehicle.snapshot())
            if ramp_done and now is not None and abs(float(now[2]) - altitude_m) <= CLIMB_DONE_M:
                return
            if time.monotonic() - t0 > timeout_s:
                raise MissionError(f"the climb to {altitude_m:.2f} m did not end within {timeout_s:.0f} s")
            await asyncio.sleep(FEED_PERIOD_S)

    def _hold_xy(self) -> NDArray[np.float64] | None:
        """Where the climb and the survey hold (map frame xy): the setpoint being streamed
        (OFFBOARD was engaged on it, at the vehicle), so a vehicle still drifting from PX4's
        take-off is brought back rather than followed; the vehicle's position before any."""
        state = self.vehicle.snapshot()
        sp = self.vehicle.offboard.status().setpoint
        frame = state.map_frame
        if sp is not None and frame is not None and self.vehicle.offboard.state.streams:
            x, y, _z = frame.from_ned(*sp.position_ned_m)
            return np.array([x, y])
        pos = position_enu(state)
        return None if pos is None else np.asarray(pos[:2], dtype=np.float64)

    def hold_at(self, xy_m: NDArray[np.floating], altitude_m: float) -> None:
        """Replace the setpoint with a hold at ``xy_m`` (map frame) and ``altitude_m``, keeping yaw."""
        snap = self.vehicle.snapshot()
        self.vehicle.offboard.set_setpoint(PositionSetpoint(
            map_frame_of(snap).to_ned(float(xy_m[0]), float(xy_m[1]), altitude_m), yaw_rad=snap.yaw_ned_rad))

    def _check_offboard(self) -> None:
        st = self.vehicle.offboard.state
        if st in (OffboardState.YIELDED, OffboardState.IDLE):
            raise MissionError(f"offboard control ended ({st.value}: {self.vehicle.offboard.failsafe.reason})")
