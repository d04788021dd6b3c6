"""Autopilot commands with COMMAND_ACK handling: retries, timeouts and named errors.

:meth:`CommandSender.command_long` sends ``COMMAND_LONG`` and waits for the matching
``COMMAND_ACK``. No answer within ``timeout_s`` resends (``confirmation`` counts up, as the
MAVLink command protocol asks) up to ``retries`` times, then raises :class:`CommandTimeoutError`.
``MAV_RESULT_IN_PROGRESS`` keeps waiting without resending. Every other non-accepted result
raises the :class:`~companion.errors.CommandError` subclass named after it, with ``result``
set to the ``MAV_RESULT`` name (``"DENIED"``, ``"TIMEOUT"``...).

:class:`VehicleCommands` adds the named helpers (``arm``, ``disarm``, ``takeoff``, ``land``,
``hold``, ``return_to_launch``, ``set_mode``, ``request_message``, ``set_message_interval``)
for a PX4 autopilot.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Iterable
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CommandError
from companion.mavlink.state import VehicleStateTracker
from companion.px4 import PX4_FORCE_DISARM_MAGIC, FlightMode, set_mode_params

log = logging.getLogger(__name__)


class CommandDeniedError(CommandError):
    """The autopilot refused the command (``MAV_RESULT_DENIED``), e.g. arming checks failed."""


class CommandTemporarilyRejectedError(CommandError):
    """Valid but not possible now (``MAV_RESULT_TEMPORARILY_REJECTED``); may work later."""


class CommandUnsupportedError(CommandError):
    """The autopilot does not know this command (``MAV_RESULT_UNSUPPORTED``)."""


class CommandFailedError(CommandError):
    """The command was executed but failed (``MAV_RESULT_FAILED``)."""


class CommandTimeoutError(CommandError):
    """No acknowledgement after every retry."""


_RESULT_ERRORS: dict[int, type[CommandError]] = {
    mavlink.MAV_RESULT_DENIED: CommandDeniedError,
    mavlink.MAV_RESULT_TEMPORARILY_REJECTED: CommandTemporarilyRejectedError,
    mavlink.MAV_RESULT_UNSUPPORTED: CommandUnsupportedError,
    mavlink.MAV_RESULT_FAILED: CommandFailedError,
}


def command_name(command: int) -> str:
    """``MAV_CMD_...`` name of a command id (the number if unknown)."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


def result_name(result: int) -> str:
    """``MAV_RESULT`` name without its prefix (``"DENIED"``)."""
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else f"UNKNOWN_{result}"


def error_for_result(command: int, result: int) -> CommandError:
    """The exception for a non-accepted ``MAV_RESULT`` of ``command``."""
    cls = _RESULT_ERRORS.get(result, CommandError)
    name = result_name(result)
    return cls(f"{command_name(command)} was not accepted: {name}", result=name)


class _Link(Protocol):
    system_id: int
    mav: mavlink.MAVLink

    def send(self, msg: mavlink.MAVLink_message) -> None: ...

    def add_listener(
        self, callback: Callable[[mavlink.MAVLink_message], None], msg_types: Iterable[str] | None = None
    ) -> Callable[[], None]: ...


class CommandSender:
    """Sends COMMAND_LONG to one target and turns its COMMAND_ACK into a return or an error.

    One command per command id is in flight at a time (acks only name the command id).
    """

    def __init__(
        self,
        link: _Link,
        target_system: int = 1,
        target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        timeout_s: float = 1.0,
        retries: int = 3,
        in_progress_timeout_s: float = 10.0,
    ) -> None:
        self.link = link
        self.target_system = target_system
        self.target_component = target_component
        self.timeout_s = timeout_s
        self.retries = retries
        self.in_progress_timeout_s = in_progress_timeout_s
        self._locks: dict[int, asyncio.Lock] = {}

    def _is_our_ack(self, command: int, msg: mavlink.MAVLink_message) -> bool:
        if msg.command != command or msg.get_srcSystem() != self.target_system:
            return False
        if self.target_component and msg.get_srcComponent() != self.target_component:
            return False
        # Older autopilots leave target_system 0; otherwise the ack must be addressed to us.
        target = getattr(msg, "target_system", 0)
        return target in (0, self.link.system_id)

    async def command_long(
        self,
        command: int,
        *params: float,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> None:
        """Send ``command`` with up to 7 params (missing ones are 0) and wait for acceptance.

        Raises :class:`CommandTimeoutError` or the error for the returned ``MAV_RESULT``.
        """
        if len(params) > 7:
            raise ValueError(f"COMMAND_LONG takes at most 7 params (got {len(params)})")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        retries = self.retries if retries is None else retries
        name = command_name(command)
        lock = self._locks.setdefault(command, asyncio.Lock())
        async with lock:
            acks: asyncio.Queue[mavlink.MAVLink_message] = asyncio.Queue()

            def on_ack(msg: mavlink.MAVLink_message) -> None:
                if self._is_our_ack(command, msg):
                    acks.put_nowait(msg)

            remove = self.link.add_listener(on_ack, ("COMMAND_ACK",))
            try:
                for attempt in range(retries + 1):
                    self.link.send(self.link.mav.command_long_encode(
                        self.target_system, self.target_component, command, attempt & 0xFF, *p
                    ))
                    result = await self._await_result(acks, timeout_s)
                    if result is None:
                        log.info("%s: no COMMAND_ACK within %.2f s (attempt %d/%d)",
                                 name, timeout_s, attempt + 1, retries + 1)
                        continue
                    if result == mavlink.MAV_RESULT_ACCEPTED:
                        log.debug("%s accepted", name)
                        return
                    err = error_for_result(command, result)
                    log.warning("%s", err)
                    raise err
            finally:
                remove()
        raise CommandTimeoutError(
            f"{name}: no COMMAND_ACK from {self.target_system}/{self.target_component} after "
            f"{retries + 1} attempts of {timeout_s:.2f} s", result="TIMEOUT"
        )

    async def _await_result(
        self, acks: asyncio.Queue[mavlink.MAVLink_message], timeout_s: float
    ) -> int | None:
        """The final MAV_RESULT, or None on timeout. IN_PROGRESS extends the wait."""
        wait_s = timeout_s
        while True:
            try:
                async with asyncio.timeout(wait_s):
                    ack = await acks.get()
            except TimeoutError:
                return None
            if ack.result == mavlink.MAV_RESULT_IN_PROGRESS:
                wait_s = self.in_progress_timeout_s
                continue
            return int(ack.result)


class VehicleCommands:
    """PX4 helpers over a :class:`CommandSender`; ``state`` supplies the home altitude."""

    def __init__(self, sender: CommandSender, state: VehicleStateTracker | None = None) -> None:
        self.sender = sender
        self.state = state

    async def arm(self, force: bool = False) -> None:
        """Arm the motors. ``force`` skips PX4's pre-arm checks (bench use only)."""
        await self.sender.command_long(
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, PX4_FORCE_DISARM_MAGIC if force else 0.0
        )

    async def disarm(self, force: bool = False) -> None:
        """Disarm. ``force`` disarms even in flight (the vehicle falls)."""
        await self.sender.command_long(
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, PX4_FORCE_DISARM_MAGIC if force else 0.0
        )

    async def takeoff(self, altitude_m: float | None = None) -> None:
        """Take off to ``altitude_m`` above home (None: PX4's ``MIS_TAKEOFF_ALT``).

        PX4 reads param7 as an AMSL altitude, so the home position must be known for an
        explicit altitude; without it PX4's default takeoff altitude applies (logged).
        """
        nan = math.nan
        alt_amsl = nan
        if altitude_m is not None:
            home = self.state.snapshot().home if self.state is not None else None
            if home is None:
                log.warning("takeoff: home position unknown; PX4's default takeoff altitude "
                            "applies instead of %.1f m", altitude_m)
            else:
                alt_amsl = home.altitude_amsl_m + altitude_m
        await self.sender.command_long(
            mavlink.MAV_CMD_NAV_TAKEOFF, nan, 0.0, 0.0, nan, nan, nan, alt_amsl
        )

    async def land(self) -> None:
        """Land where the vehicle is."""
        nan = math.nan
        await self.sender.command_long(mavlink.MAV_CMD_NAV_LAND, 0.0, 0.0, 0.0, nan, nan, nan, nan)

    async def return_to_launch(self) -> None:
        """Fly home and land (PX4 RTL)."""
        await self.sender.command_long(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)

    async def hold(self) -> None:
        """Hold position (PX4 AUTO.LOITER)."""
        await self.set_mode(FlightMode.HOLD)

    async def request_message(self, msg_id: int) -> None:
        """Ask for one message now (``MAV_CMD_REQUEST_MESSAGE``), e.g. HOME_POSITION."""
        await self.sender.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, float(msg_id))

    async def set_message_interval(self, msg_id: int, rate_hz: float) -> None:
        """Stream ``msg_id`` at ``rate_hz`` (0 stops it) with ``MAV_CMD_SET_MESSAGE_INTERVAL``."""
        if rate_hz < 0:
            raise ValueError(f"message rate must be >= 0 Hz (got {rate_hz})")
        interval_us = -1.0 if rate_hz == 0 else 1e6 / rate_hz
        await self.sender.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)

    async def set_mode(self, mode: FlightMode) -> None:
        """Switch PX4 to ``mode`` with ``MAV_CMD_DO_SET_MODE`` (custom main/sub mode)."""
        await self.sender.command_long(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(mode))
