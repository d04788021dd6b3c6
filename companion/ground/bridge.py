"""The MQTT ground link: publishes the vehicle's state, receives validated commands.

::

    async with MqttBridge.from_config(cfg) as bridge:     # cfg: CompanionConfig
        bridge.publish_status("mapping", uptime_s=12.0, stage_timings_ms={"perception": 40.1})
        async for cmd in bridge.commands():      # GoalCommand | MissionCommand | VehicleCommand
            ...

Publishing never blocks and never raises on network trouble: ``publish_*`` put the message in
an outbox and return. The outbox keeps the latest value of every state topic (status,
telemetry, objects, map, path), so a ground station is never shown stale state after a
reconnect - all of them are sent again on each connection - and a bounded queue of events
(command replies) that drops the oldest, with a warning, when full. While the broker is
unreachable the bridge retries with exponential backoff and the service keeps flying.

Every command goes through :class:`~companion.ground.validation.CommandValidator`; the
sender gets a reply on ``<base>/reply`` (``ok`` true, or false with the reason), and only
accepted commands reach :meth:`MqttBridge.commands`. Malformed payloads never raise out of
the bridge. aiomqtt errors are turned into :class:`GroundLinkError` at this boundary and
logged; :attr:`MqttBridge.last_error` keeps the latest one. Call the ``publish_*`` methods
from the event loop's thread.
"""

from __future__ import annotations

import asyncio
import logging
import random
import ssl
import time
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import aiomqtt
import numpy as np
from numpy.typing import NDArray
from paho.mqtt.subscribeoptions import SubscribeOptions
from pydantic import BaseModel, ValidationError

from companion.background import TASK_STOP_TIMEOUT_S, end_task, stop_tasks
from companion.config import CompanionConfig, MqttConfig
from companion.errors import GroundLinkError
from companion.ground import connection
from companion.ground.messages import (
    ObjectItem,
    ObjectsMessage,
    encode,
    map_message,
    object_items,
    online_message,
    path_message,
    reply_message,
    status_message,
    telemetry_message,
)
from companion.ground.schema import Command, Rejection, Topics, command_kind_of, peek_request_id
from companion.ground.validation import CommandValidator
from semmap.costmap import Costmap, ObjectFootprint


@dataclass(frozen=True)
class _Outgoing:
    topic: str
    payload: bytes
    qos: int
    retain: bool


@dataclass
class LinkStats:
    """Counters of the ground link, for the status message and for tests."""

    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0
    published: int = 0
    dropped_events: int = 0
    commands_accepted: int = 0
    commands_rejected: int = 0


def _as_is(msg: BaseModel) -> BaseModel:
    """The builder for a message that is already built."""
    return msg


class MqttBridge:
    """Async context manager owning the connection to the broker (see the module doc).

    ``cfg``: the ``mqtt`` config section. ``validator``: limits applied to every command.
    ``logger``: where the bridge logs (default: this module's logger). ``clock``: monotonic
    seconds, for the map rate. ``client_id``: MQTT client id (default
    ``companion-<vehicle_id>``).
    """

    def __init__(
        self,
        cfg: MqttConfig,
        validator: CommandValidator,
        *,
        logger: logging.Logger | None = None,
        clock: Callable[[], float] = time.monotonic,
        client_id: str | None = None,
    ) -> None:
        self.cfg = cfg
        self.topics = Topics(cfg.topic_prefix, cfg.vehicle_id)
        self.validator = validator
        self.stats = LinkStats()
        #: The latest connection failure (None while connected or before the first try).
        self.last_error: GroundLinkError | None = None
        self._log = logger or logging.getLogger(__name__)
        self._clock = clock
        self._client_id = client_id or f"companion-{cfg.vehicle_id}"
        self._password: str | None = None
        self._tls: ssl.SSLContext | None = None
        # State topics: latest payload per topic; a version number tells the sender whether
        # the value changed while it was being published.
        self._state: dict[str, tuple[_Outgoing, int]] = {}
        self._dirty: dict[str, None] = {}  # insertion-ordered set of topics to (re)send
        self._version = 0
        self._events: deque[_Outgoing] = deque()
        self._wake = asyncio.Event()
        self._connected = asyncio.Event()
        self._closed = asyncio.Event()
        self._commands: asyncio.Queue[Command] = asyncio.Queue(maxsize=cfg.command_queue_size)
        self._last_objects: list[ObjectItem] | None = None
        self._pending_map: Costmap | None = None
        self._map_pending = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._client: aiomqtt.Client | None = None
        self._up_since_s: float | None = None
        self._rng = random.Random()

    @classmethod
    def from_config(
        cls, cfg: CompanionConfig, *, logger: logging.Logger | None = None
    ) -> "MqttBridge":
        """The bridge for a whole configuration: ``mqtt`` settings, ``planner`` limits."""
        return cls(cfg.mqtt, CommandValidator.from_config(cfg.planner, cfg.mqtt), logger=logger)

    # --- lifecycle ----------------------------------------------------------------------

    async def __aenter__(self) -> "MqttBridge":
        """Check credentials and TLS files (raising :class:`GroundLinkError`), then connect
        in the background; returns at once, connected or not."""
        if self.cfg.password_file is not None:
            self._password = connection.read_password_file(self.cfg.password_file)
        self._tls = connection.make_tls_context(self.cfg)
        self._closed.clear()
        self._tasks = [asyncio.create_task(self._map_loop(), name="mqtt-map")]
        if self.cfg.enabled:
            self._tasks.append(asyncio.create_task(self._run(), name="mqtt-link"))
        else:
            self._log.info("ground link disabled (mqtt.enabled is false)")
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._closed.set()
        client = self._client
        if client is not None and self.connected:
            # Say goodbye on purpose; the last will is only for unexpected losses.
            offline = encode(online_message(self.cfg.vehicle_id, False))
            try:
                await asyncio.wait_for(
                    client.publish(self.topics.online, offline, qos=1, retain=True),
                    self.cfg.timeout_s,
                )
            except (aiomqtt.MqttError, asyncio.TimeoutError) as err:
                self._log.warning("ground link: could not publish offline: %s", err)
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            await end_task(task, f"the ground link's {task.get_name()} loop")

    @property
    def connected(self) -> bool:
        """True while a session with the broker is up."""
        return self._connected.is_set()

    async def wait_connected(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a session; True if connected."""
        try:
            await asyncio.wait_for(self._connected.wait(), timeout_s)
        except asyncio.TimeoutError:
            return False
        return True

    # --- publishing (never blocks, never raises on network trouble) ---------------------

    def publish_status(
        self,
        state: str,
        uptime_s: float,
        stage_timings_ms: Mapping[str, float] | None = None,
        health: Mapping[str, bool] | None = None,
        detail: str | None = None,
    ) -> bool:
        """Queue a ``status`` message (call at 1 Hz). False if the values were invalid."""
        return self._put_state(
            "status", self.topics.status, 0, False, status_message,
            self.cfg.vehicle_id, state, uptime_s, stage_timings_ms, health, detail,
        )

    def publish_telemetry(
        self,
        xyz_map_m: NDArray[np.floating] | Iterable[float],
        velocity_map_m_s: NDArray[np.floating] | Iterable[float],
        yaw_rad: float,
        armed: bool,
        in_air: bool,
        flight_mode: str,
        battery_remaining_pct: float | None = None,
    ) -> bool:
        """Queue a ``telemetry`` message: map-frame (ENU) position (3,) m, velocity (3,) m/s,
        ENU yaw in radians. Call at 5 Hz. False if the values were invalid (e.g. NaN)."""
        return self._put_state(
            "telemetry", self.topics.telemetry, 0, False, telemetry_message,
            self.cfg.vehicle_id, xyz_map_m, velocity_map_m_s, yaw_rad, armed, in_air,
            flight_mode, battery_remaining_pct,
        )

    def publish_objects(self, objects: Iterable[ObjectFootprint]) -> bool:
        """Queue the object list (retained) if it differs from the last one; True if queued."""
        try:
            items = object_items(objects)
        except (ValidationError, ValueError, TypeError) as exc:
            self._log.warning("ground link: not publishing objects: %s", exc)
            return False
        if items == self._last_objects:
            return False
        msg = ObjectsMessage(vehicle_id=self.cfg.vehicle_id, stamp_s=time.time(), objects=items)
        if not self._put_state("objects", self.topics.objects, 1, True, _as_is, msg):
            return False
        self._last_objects = items
        return True

    def publish_map(self, costmap: Costmap) -> None:
        """Offer the latest costmap; it is published (retained) at most ``mqtt.map_rate_hz``.

        Call it whenever the map changes: the newest one offered is the one sent when the
        rate allows. ``costmap`` must not be modified afterwards (it is encoded later).
        """
        self._pending_map = costmap
        self._map_pending.set()

    def publish_path(
        self,
        waypoints_xyz_map_m: NDArray[np.floating] | Iterable[Iterable[float]],
        request_id: str | None = None,
    ) -> bool:
        """Queue the current path (retained): (N, 3) map-frame waypoints, N = 0 for none."""
        return self._put_state(
            "path", self.topics.path, 1, True, path_message,
            self.cfg.vehicle_id, waypoints_xyz_map_m, request_id,
        )

    def publish_reply(
        self, kind: str, ok: bool, request_id: str | None, reason: str | None = None
    ) -> None:
        """Queue a reply to a command (the bridge replies to validation itself; the service
        uses this to report a later outcome, e.g. that no path exists)."""
        msg = reply_message(self.cfg.vehicle_id, kind, ok, request_id, reason)
        self._put_event(_Outgoing(self.topics.reply, encode(msg), 1, False))

    # --- commands -----------------------------------------------------------------------

    async def commands(self) -> AsyncIterator[Command]:
        """Validated commands, in arrival order, until the bridge is closed."""
        while not self._closed.is_set():
            get = asyncio.ensure_future(self._commands.get())
            closed = asyncio.ensure_future(self._closed.wait())
            try:
                await asyncio.wait((get, closed), return_when=asyncio.FIRST_COMPLETED)
            finally:
                closed.cancel()
                if not get.done():
                    get.cancel()
            if get.done() and not get.cancelled():
                yield get.result()

    def handle_message(self, topic: str, payload: Any, retain: bool = False) -> None:
        """Process one received message: validate it, reply, queue it if accepted.

        Never raises: whatever arrives, the sender gets a reply with the reason.
        """
        try:
            self._handle_message(topic, payload, retain)
        except Exception as exc:  # a bug here must not take the link down
            self._log.exception("ground link: error handling a message on %s", topic)
            kind = self.topics.command_kind(topic)
            if kind is not None:
                self.stats.commands_rejected += 1
                self.publish_reply(kind, False, None,
                                   f"{kind}: internal error ({type(exc).__name__}); not executed")

    def _handle_message(self, topic: str, payload: Any, retain: bool) -> None:
        kind = self.topics.command_kind(topic)
        if kind is None:
            return
        raw = payload if isinstance(payload, (bytes, bytearray, str)) else str(payload)
        if len(raw) == 0:
            # An empty message is how MQTT clears a retained one: not a command, no reply.
            self._log.debug("ground link: ignoring an empty message on %s", topic)
            return
        if retain:
            # A retained command would run again on every reconnect: refuse it.
            result: Command | Rejection = Rejection(
                kind, f"{kind}: retained commands are refused (publish with retain=false)",
                peek_request_id(raw),
            )
        else:
            result = self.validator.validate(kind, raw)
        if isinstance(result, Rejection):
            self.stats.commands_rejected += 1
            self._log.warning("ground link: refused %s command %s: %s",
                              kind, result.request_id, result.reason)
            self.publish_reply(kind, False, result.request_id, result.reason)
            return
        try:
            self._commands.put_nowait(result)
        except asyncio.QueueFull:
            self.stats.commands_rejected += 1
            reason = f"service busy: {self._commands.qsize()} commands waiting"
            self._log.warning("ground link: refused %s command %s: %s",
                              kind, result.request_id, reason)
            self.publish_reply(kind, False, result.request_id, reason)
            return
        self.stats.commands_accepted += 1
        self._log.info("ground link: accepted %s command %s", command_kind_of(result),
                       result.request_id)
        self.publish_reply(kind, True, result.request_id)

    # --- the outbox ---------------------------------------------------------------------

    def _put_state(
        self, name: str, topic: str, qos: int, retain: bool,
        build: Callable[..., BaseModel], *args: Any,
    ) -> bool:
        try:
            payload = encode(build(*args))
        except (ValidationError, ValueError, TypeError) as exc:
            self._log.warning("ground link: not publishing %s: %s", name, exc)
            return False
        self._version += 1
        self._state[topic] = (_Outgoing(topic, payload, qos, retain), self._version)
        self._dirty[topic] = None
        self._wake.set()
        return True

    def _put_event(self, item: _Outgoing) -> None:
        if len(self._events) >= self.cfg.outbox_size:
            dropped = self._events.popleft()
            self.stats.dropped_events += 1
            self._log.warning(
                "ground link: outbox full (%d events), dropped the oldest on %s (%d dropped so far)",
                self.cfg.outbox_size, dropped.topic, self.stats.dropped_events,
            )
        self._events.append(item)
        self._wake.set()

    async def _send_pending(self, client: aiomqtt.Client) -> None:
        """Publish queued events, then every dirty state topic, until nothing is left."""
        while True:
            if self._events:
                item = self._events[0]
                await client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain)
                if self._events and self._events[0] is item:
                    self._events.popleft()
            elif self._dirty:
                topic = next(iter(self._dirty))
                item, version = self._state[topic]
                await client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain)
                if self._state[topic][1] == version:
                    self._dirty.pop(topic, None)
            else:
                return
            self.stats.published += 1

    async def _send_loop(self, client: aiomqtt.Client) -> None:
        while True:
            self._wake.clear()
            await self._send_pending(client)
            await self._wake.wait()

    async def _map_loop(self) -> None:
        """Encode and queue the newest offered costmap, at most ``map_rate_hz``."""
        period_s = 1.0 / self.cfg.map_rate_hz
        last_s: float | None = None
        while True:
            await self._map_pending.wait()
            if last_s is not None:
                wait_s = last_s + period_s - self._clock()
                if wait_s > 0.0:
                    await asyncio.sleep(wait_s)
            costmap, self._pending_map = self._pending_map, None
            self._map_pending.clear()
            if costmap is None:
                continue
            last_s = self._clock()
            try:
                # PNG encoding of a large grid takes milliseconds: keep it off the loop.
                msg = await asyncio.to_thread(map_message, self.cfg.vehicle_id, costmap)
            except (ValidationError, ValueError) as exc:
                self._log.warning("ground link: not publishing map: %s", exc)
                continue
            self._put_state("map", self.topics.map, 1, True, _as_is, msg)

    # --- the connection -----------------------------------------------------------------

    async def _run(self) -> None:
        """Connect, run a session, and reconnect with exponential backoff, forever.

        The backoff restarts from ``reconnect_min_s`` only after a session that lasted at
        least ``reconnect_max_s``, so a broker that accepts and then drops us at once (a
        duplicate client id, an overloaded broker) is not hammered.
        """
        delay_s = self.cfg.reconnect_min_s
        while True:
            try:
                client = connection.make_client(self.cfg, client_id=self._client_id, password=self._password,
                                     tls=self._tls, online_topic=self.topics.online, logger=self._log)
                async with client:
                    await self._session(client)
            except aiomqtt.MqttError as exc:
                err = connection.describe_failure(self.cfg, exc)
            except Exception as exc:  # never let the link take the service down
                self._log.exception("ground link: unexpected error")
                err = GroundLinkError(f"MQTT ground link: unexpected {type(exc).__name__}: {exc}")
            else:
                err = GroundLinkError(f"MQTT broker {self.cfg.host}:{self.cfg.port}: session ended")
            finally:
                self._client = None
                up_since_s, self._up_since_s = self._up_since_s, None
                if self._connected.is_set():
                    self._connected.clear()
                    self.stats.disconnects += 1
            self.last_error = err
            if up_since_s is None:
                self.stats.connect_failures += 1
            elif self._clock() - up_since_s >= self.cfg.reconnect_max_s:
                delay_s = self.cfg.reconnect_min_s
            wait_s = delay_s * self._rng.uniform(0.8, 1.2)
            self._log.warning("ground link down: %s; retrying in %.1f s", err, wait_s)
            await asyncio.sleep(wait_s)
            delay_s = min(delay_s * 2.0, self.cfg.reconnect_max_s)

    async def _session(self, client: aiomqtt.Client) -> None:
        """One connected session: subscribe, announce, resend state, then pump both ways."""
        granted = await client.subscribe(
            self.topics.command_filter,
            options=SubscribeOptions(qos=1, retainAsPublished=True),
        )
        if any(getattr(rc, "is_failure", False) or rc == 0x80 for rc in granted):
            # Some brokers refuse a subscription their ACL forbids; state still goes out.
            self._log.error("ground link: the broker refused the subscription to %s: "
                            "no commands will arrive (check the broker's ACL for %s)",
                            self.topics.command_filter, self.cfg.username or "anonymous")
        await client.publish(
            self.topics.online, encode(online_message(self.cfg.vehicle_id, True)),
            qos=1, retain=True,
        )
        self.stats.connects += 1
        self.last_error = None
        for topic in self._state:  # the broker may have lost everything (restart)
            self._dirty[topic] = None
        self._client = client
        self._up_since_s = self._clock()
        self._connected.set()
        self._log.info("ground link up: %s:%d as %s, commands on %s",
                       self.cfg.host, self.cfg.port, self._client_id, self.topics.command_filter)
        receiver = asyncio.create_task(self._receive_loop(client), name="mqtt-receive")
        sender = asyncio.create_task(self._send_loop(client), name="mqtt-send")
        try:
            done, _ = await asyncio.wait((receiver, sender), return_when=asyncio.FIRST_COMPLETED)
        finally:
            # Cancelled again until they end: Python 3.11's wait_for (in aiomqtt's publish)
            # swallows a cancellation that arrives together with the PUBACK.
            await stop_tasks((receiver, sender), TASK_STOP_TIMEOUT_S, "ending the ground link's session")
            for task in (receiver, sender):
                exc = task.exception() if task.done() and not task.cancelled() else None
                if exc is not None and not isinstance(exc, aiomqtt.MqttError):
                    raise exc
        for task in done:
            task.result()  # re-raise what ended the session (usually MqttError)

    async def _receive_loop(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            self.handle_message(message.topic.value, message.payload, bool(message.retain))
