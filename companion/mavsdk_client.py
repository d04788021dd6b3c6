"""Mission transfer through the MAVSDK library (the native ``mavsdk`` 4.x binding).

MAVSDK 4 ships its C++ core inside the wheel (``mavsdk/lib/libcmavsdk.so``, no separate
``mavsdk_server``); ``mavsdk.asyncio`` wraps it: ``Mavsdk(Configuration)`` owns the core,
``add_any_connection(url)`` opens a link, ``first_autopilot(timeout_s)`` returns a ``System``,
and plugins are built from the system (``MissionRawAsync(system)``).

We use the *raw* mission plugin so each MAVLink item we build maps 1:1 to a sequence number on
the vehicle. MAVSDK's upload result does not say which item failed, so during an upload we also
watch the autopilot's ``MISSION_REQUEST_INT`` messages (``MavlinkDirect`` plugin): the last
item requested is the one it rejected or never received, and the error names that waypoint.

Every MAVSDK failure is converted at this boundary: connection problems to
:class:`~companion.errors.LinkError`, transfer problems to :class:`~companion.errors.MissionError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from typing import Any

from mavsdk import LogLevel, log_subscribe
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.action import ActionError
from mavsdk.plugins.mission_raw import MissionItem as RawItem
from mavsdk.plugins.mission_raw import MissionPlan as RawPlan
from mavsdk.plugins.mission_raw import MissionRawError, MissionRawResult
from mavsdk.plugins.telemetry import TelemetryError

from companion.errors import CommandError, LinkError, MissionError
from companion.geo import GeoOrigin
from companion.mission_validation import check_plan
from companion.missions import (
    ItemMap,
    MissionItemInt,
    MissionPlan,
    command_name,
    items_to_plan,
    plan_to_items,
)

log = logging.getLogger(__name__)

_EXPLAIN = {
    MissionRawResult.DENIED: "the autopilot denied the item",
    MissionRawResult.UNSUPPORTED: "the autopilot does not support this item",
    MissionRawResult.TIMEOUT: "no answer from the autopilot (link lost?)",
    MissionRawResult.TOO_MANY_MISSION_ITEMS: "too many items for the autopilot",
    MissionRawResult.BUSY: "another mission transfer is in progress",
    MissionRawResult.INVALID_SEQUENCE: "the autopilot asked for items out of order",
    MissionRawResult.NO_SYSTEM: "no autopilot connected",
    MissionRawResult.PROTOCOL_ERROR: "MAVLink mission protocol error",
    MissionRawResult.INVALID_ARGUMENT: "an item has an invalid parameter",
    MissionRawResult.NO_MISSION_AVAILABLE: "the vehicle has no mission",
}


_mavsdk_log = logging.getLogger("mavsdk")
_LOG_LEVELS = {LogLevel.DEBUG: logging.DEBUG, LogLevel.INFO: logging.INFO,
               LogLevel.WARN: logging.WARNING, LogLevel.ERROR: logging.ERROR}
_logs_routed = False


def _on_mavsdk_log(level: LogLevel, message: str, file: str | None, line: int) -> bool:
    _mavsdk_log.log(_LOG_LEVELS.get(level, logging.INFO), "%s", message)
    return True  # handled: MAVSDK does not print it to stdout


def route_mavsdk_logs() -> None:
    """Send MAVSDK core's log lines to the ``mavsdk`` Python logger instead of stdout."""
    global _logs_routed
    if not _logs_routed:
        log_subscribe(_on_mavsdk_log)
        _logs_routed = True


def _to_raw(it: MissionItemInt) -> RawItem:
    return RawItem(it.seq, it.frame, it.command, it.current, it.autocontinue, it.param1,
                   it.param2, it.param3, it.param4, it.x, it.y, it.z, it.mission_type)


def _from_raw(it: Any) -> MissionItemInt:
    return MissionItemInt(int(it.seq), int(it.frame), int(it.command), int(it.current),
                          int(it.autocontinue), float(it.param1), float(it.param2),
                          float(it.param3), float(it.param4), int(it.x), int(it.y), float(it.z),
                          int(it.mission_type))


def _home(h: Any) -> GeoOrigin:
    # MAVSDK passes the altitude through a float32: round off the noise (to a millimetre).
    return GeoOrigin(h.latitude_deg, h.longitude_deg, round(h.absolute_altitude_m, 3))


def _result_text(result: Any) -> str:
    name = getattr(result, "name", str(result))
    explain = _EXPLAIN.get(result)
    return f"{name} ({explain})" if explain else name


class MavsdkClient:
    """A MAVSDK session with one autopilot: ``async with MavsdkClient(url) as c:``.

    ``url`` is a MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyTHS1:921600``).
    Raises :class:`LinkError` from ``__aenter__`` if no autopilot is heard within
    ``connect_timeout_s``.
    """

    def __init__(self, url: str = "udpin://0.0.0.0:14540", connect_timeout_s: float = 10.0,
                 transfer_timeout_s: float = 60.0) -> None:
        self.url = url
        self.connect_timeout_s = connect_timeout_s
        self.transfer_timeout_s = transfer_timeout_s
        self._sdk: Mavsdk | None = None
        self._system: Any = None
        self._plugins: dict[str, Any] = {}

    async def __aenter__(self) -> MavsdkClient:
        route_mavsdk_logs()
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        self._sdk = Mavsdk(config)
        try:
            await self._sdk.add_any_connection(self.url)
        except MavsdkConnectionError as exc:
            self._close()
            raise LinkError(f"MAVSDK cannot open {self.url}: {exc}") from exc
        try:
            system = await self._sdk.first_autopilot(timeout_s=self.connect_timeout_s)
        except BaseException:  # cancelled (Ctrl-C): do not leak the native core
            self._close()
            raise
        if system is None:
            self._close()
            raise LinkError(f"no autopilot heard on {self.url} within "
                            f"{self.connect_timeout_s:g} s")
        self._system = system
        # Telemetry caches what arrives only from its creation on: create it now so the home
        # position MAVSDK asks for while connecting is there when an upload needs it.
        _ = self.telemetry
        log.info("MAVSDK connected to autopilot on %s", self.url)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._close()

    def _close(self) -> None:
        # Destroy plugins here, on this thread, before the core. Left to the garbage collector
        # their __del__ can run on an executor thread (the last reference is often a finished
        # run_in_executor call) while Mavsdk.destroy() runs here, and the native core aborts.
        for plugin in self._plugins.values():
            plugin.destroy()
        if self._sdk is not None:
            self._sdk.destroy()
            self._sdk = None
        self._plugins.clear()
        self._system = None

    # --- plugins -------------------------------------------------------------------------

    def _plugin(self, name: str, cls: Any) -> Any:
        if self._system is None:
            raise LinkError("MAVSDK client is not connected (use 'async with')")
        if name not in self._plugins:
            self._plugins[name] = cls(self._system)
        return self._plugins[name]

    @property
    def telemetry(self) -> TelemetryAsync:
        return self._plugin("telemetry", TelemetryAsync)  # type: ignore[no-any-return]

    @property
    def action(self) -> ActionAsync:
        return self._plugin("action", ActionAsync)  # type: ignore[no-any-return]

    @property
    def offboard(self) -> OffboardAsync:
        return self._plugin("offboard", OffboardAsync)  # type: ignore[no-any-return]

    @property
    def mavlink_direct(self) -> MavlinkDirectAsync:
        return self._plugin("mavlink_direct", MavlinkDirectAsync)  # type: ignore[no-any-return]

    @property
    def mission_raw(self) -> MissionRawAsync:
        return self._plugin("mission_raw", MissionRawAsync)  # type: ignore[no-any-return]

    # --- actions -------------------------------------------------------------------------

    async def arm(self) -> None:
        """Arm the vehicle. Raises :class:`CommandError` with MAVSDK's result name."""
        try:
            await self.action.arm()
        except ActionError as exc:
            name = getattr(exc.result, "name", str(exc.result))
            raise CommandError(f"arming refused by the autopilot: {name}", name) from exc

    # --- queries -------------------------------------------------------------------------

    async def home(self, timeout_s: float = 5.0) -> GeoOrigin:
        """The vehicle's home position (HOME_POSITION), waiting up to ``timeout_s``."""
        try:
            h = await self.telemetry.home()  # the latest value, if one arrived already
            if math.isfinite(h.latitude_deg) and math.isfinite(h.longitude_deg) and \
                    (h.latitude_deg != 0.0 or h.longitude_deg != 0.0):
                return _home(h)
        except Exception as exc:  # noqa: BLE001 - MAVSDK raises TelemetryError or returns NaN
            log.debug("no cached home position yet: %s", exc)
        try:
            # Ask for it now rather than wait for the next slow periodic HOME_POSITION.
            await self.telemetry.set_rate_home(1.0)
        except TelemetryError as exc:
            log.debug("set_rate_home refused: %s", exc)
        gen = self.telemetry.subscribe_home()
        try:
            async with asyncio.timeout(timeout_s):
                async for h in gen:
                    if math.isfinite(h.latitude_deg) and math.isfinite(h.longitude_deg):
                        return _home(h)
        except TimeoutError as exc:
            raise LinkError(f"no home position from the autopilot on {self.url} within "
                            f"{timeout_s:g} s") from exc
        finally:
            await gen.aclose()
        raise LinkError("home position stream ended")

    # --- missions ------------------------------------------------------------------------

    async def upload_mission(self, plan: MissionPlan) -> ItemMap:
        """Upload ``plan`` (local waypoints are resolved around the vehicle's home).

        Returns the MAVLink items sent. Raises :class:`MissionError` naming the waypoint the
        autopilot rejected, or :class:`LinkError` if the link fails.
        """
        vehicle_home = await self.home() if plan.home is None else None
        resolved = check_plan(plan.resolved(vehicle_home))
        imap = plan_to_items(resolved)
        if not imap.items:
            raise MissionError(f"{plan.source}: the mission has no items")
        raw = RawPlan([_to_raw(it) for it in imap.items])
        requested: list[int] = []
        watcher = asyncio.create_task(self._watch_requests(requested))
        progress = 0.0
        try:
            async with asyncio.timeout(self.transfer_timeout_s):
                async for _result, data in self.mission_raw.upload_mission_with_progress(raw):
                    if data is not None and math.isfinite(data.progress):
                        progress = data.progress
        except MissionRawError as exc:
            await asyncio.sleep(0.05)  # let the last MISSION_REQUEST_INT callback land
            seq = requested[-1] if requested else int(round(progress * len(imap.items)))
            raise self._upload_error(plan, imap, seq, exc.result) from exc
        except TimeoutError as exc:
            raise MissionError(f"{plan.source}: upload did not finish within "
                               f"{self.transfer_timeout_s:g} s") from exc
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
        log.info("uploaded %d mission items (%d waypoints) from %s", len(imap.items),
                 len(plan.waypoints), plan.source)
        return imap

    async def _watch_requests(self, requested: list[int]) -> None:
        """Append the ``seq`` of every MISSION_REQUEST_INT the autopilot sends."""
        gen = self.mavlink_direct.subscribe_message("MISSION_REQUEST_INT")
        try:
            async for msg in gen:
                try:
                    requested.append(int(json.loads(msg.fields_json)["seq"]))
                except (ValueError, KeyError, TypeError):
                    log.debug("unreadable MISSION_REQUEST_INT: %r", msg.fields_json)
        finally:
            await gen.aclose()

    def _upload_error(self, plan: MissionPlan, imap: ItemMap, seq: int,
                      result: Any) -> MissionError:
        n = len(imap.items)
        seq = min(n - 1, max(0, seq))
        wp = imap.waypoint_index[seq]
        item = imap.items[seq]
        return MissionError(
            f"{plan.source}: upload failed at MAVLink item {seq} of {n} (waypoint {wp}, "
            f"{plan.waypoints[wp].action}, command {command_name(item.command)}): "
            f"{_result_text(result)}")

    async def download_mission(self) -> MissionPlan:
        """The vehicle's current mission as a plan (home from the vehicle)."""
        try:
            async with asyncio.timeout(self.transfer_timeout_s):
                items = await self.mission_raw.download_mission()
        except MissionRawError as exc:
            raise MissionError(f"mission download from {self.url} failed: "
                               f"{_result_text(exc.result)}") from exc
        except TimeoutError as exc:
            raise MissionError(f"mission download from {self.url} did not finish within "
                               f"{self.transfer_timeout_s:g} s") from exc
        home = await self.home()
        return items_to_plan([_from_raw(it) for it in items], home, f"vehicle at {self.url}")

    async def clear_mission(self) -> None:
        """Delete the vehicle's mission."""
        try:
            await self.mission_raw.clear_mission()
        except MissionRawError as exc:
            raise MissionError(f"clearing the mission failed: {_result_text(exc.result)}") from exc

    async def start_mission(self) -> None:
        """Switch the vehicle to Mission mode (it must be armed to fly)."""
        try:
            await self.mission_raw.start_mission()
        except MissionRawError as exc:
            raise MissionError(f"starting the mission failed: {_result_text(exc.result)}") from exc

    async def wait_mission_finished(self, timeout_s: float) -> None:
        """Wait until the vehicle reports the last item reached."""
        gen = self.mission_raw.subscribe_mission_progress()
        try:
            async with asyncio.timeout(timeout_s):
                async for prog in gen:
                    log.info("mission progress %d/%d", prog.current, prog.total)
                    if prog.total > 0 and prog.current >= prog.total:
                        return
        except TimeoutError as exc:
            raise MissionError(f"mission not finished within {timeout_s:g} s") from exc
        finally:
            await gen.aclose()
