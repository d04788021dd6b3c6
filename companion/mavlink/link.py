"""The MAVLink link: our one typed adapter over pymavlink.

:class:`MavlinkLink` is an async context manager that opens a transport (see
:mod:`companion.mavlink.transport`), parses every received chunk with pymavlink's MAVLink 2
parser inside the event loop (no blocking ``recv_match``; every message of a datagram is
dispatched), sends our own 1 Hz heartbeat as an onboard computer, and optionally signs
outgoing messages (MAVLink 2 signing, key from a file).

Consumers either register a synchronous listener (called for every matching message, used
by the vehicle-state tracker and command acknowledgement) or iterate a
:class:`Subscription`, an async iterator over a bounded queue that drops its oldest message
(and logs) when the consumer is slow::

    async with MavlinkLink("udpin://0.0.0.0:14540") as link:
        async with link.subscribe("HEARTBEAT") as heartbeats:
            async for msg in heartbeats:
                ...

Messages are built with the encoder ``link.mav`` (``link.mav.heartbeat_encode(...)``) and
MAVLink enums are named through :data:`mavlink` (pymavlink's MAVLink 2 common dialect).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

from companion.background import BackgroundTasks
from companion.errors import ConfigError, LinkError
from companion.mavlink.signing import SIGNING_KEY_BYTES, read_key_file
from companion.mavlink.subscription import Message, Subscription
from companion.mavlink.tlog import TlogWriter
from companion.mavlink.transport import UdpTransport, make_transport
from companion.mavlink.transport_base import Transport
from companion.mavlink.urls import parse_url

if TYPE_CHECKING:
    from companion.config import LinkConfig

log = logging.getLogger(__name__)

Listener = Callable[[Message], None]

#: Seconds between 1970-01-01 and the MAVLink signing epoch (2015-01-01 00:00:00 UTC).
_SIGNING_EPOCH_UNIX_S = 1420070400
DEFAULT_QUEUE_SIZE = 64


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink 2 message signing: sign what we send and reject unsigned/badly signed input.

    ``allow_unsigned_ids``: message ids accepted without a valid signature (the MAVLink
    guide suggests RADIO_STATUS, which radios inject unsigned).
    """

    key: bytes
    link_id: int = 0
    allow_unsigned_ids: frozenset[int] = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})

    def __post_init__(self) -> None:
        if len(self.key) != SIGNING_KEY_BYTES:
            raise ConfigError(f"MAVLink signing key must be {SIGNING_KEY_BYTES} bytes (got {len(self.key)})")
        if not 0 <= self.link_id <= 255:
            raise ConfigError(f"MAVLink signing link_id must be 0..255 (got {self.link_id})")


def load_signing_key(path: str | Path) -> bytes:
    """Read a 32-byte signing key file (see :mod:`companion.mavlink.signing`).

    Raises :class:`ConfigError` naming the file when it is missing, malformed or readable by
    others than its owner.
    """
    return read_key_file(path)


def signing_timestamp_now() -> int:
    """The MAVLink signing timestamp for 'now': 10 us units since 2015-01-01 UTC."""
    return int((time.time() - _SIGNING_EPOCH_UNIX_S) * 100_000)


@dataclass(frozen=True)
class LinkStats:
    """Counters since the link opened.

    ``garbage_dropped``: datagrams from other addresses than the peer that were not MAVLink;
    ``strangers_dropped``: MAVLink datagrams from other addresses (another system, or the
    autopilot's ids while the peer is alive, or unsigned with signing on), ignored;
    ``peer``: the address the link is locked to (UDP in), ``peer_changes``: how often it was set.
    """

    messages_received: int
    messages_sent: int
    bad_data: int
    send_dropped: int
    queue_dropped: int
    signature_rejected: int
    garbage_dropped: int = 0
    strangers_dropped: int = 0
    peer: str | None = None
    peer_changes: int = 0


def first_packet_ids(data: bytes) -> tuple[int, int] | None:
    """``(system id, component id)`` of the MAVLink packet a datagram starts with, or None
    when it cannot start with a whole one (a few byte reads: garbage is dropped this cheaply)."""
    n = len(data)
    if n >= 12 and data[0] == mavlink.PROTOCOL_MARKER_V2:
        size = 12 + data[1] + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if data[2] & mavlink.MAVLINK_IFLAG_SIGNED else 0)
        return (data[5], data[6]) if size <= n else None
    if n >= 8 and data[0] == mavlink.PROTOCOL_MARKER_V1:
        return (data[3], data[4]) if 8 + data[1] <= n else None
    return None


class _Writer:
    """The file-like object pymavlink's encoder writes packed messages into."""

    def __init__(self) -> None:
        self.transport: Transport | None = None

    def write(self, buf: bytes) -> None:
        if self.transport is None:
            raise LinkError("MAVLink link is not open")
        self.transport.send(bytes(buf))


class MavlinkLink:
    """An open MAVLink 2 connection with our identity and heartbeat (async context manager).

    ``system_id``/``component_id``: our identity (the vehicle's system id and
    ``MAV_COMP_ID_ONBOARD_COMPUTER``). ``heartbeat_rate_hz``: our heartbeat (0 = none, for
    passive tools). ``signing``: MAVLink 2 signing, or None for off. ``record_path``: append
    every valid received packet to this ``.tlog`` (replay it later with ``tlog://``).

    With ``udpin`` the link is locked to one peer: the first address that sends a valid
    MAVLink packet from ``peer_system`` (any system when None) and ``peer_component`` (any
    when 0), signed when signing is on. Datagrams from any other address are counted and
    dropped; another address becomes the peer only after the peer was silent for
    ``peer_timeout_s``.
    """

    def __init__(
        self,
        url: str,
        *,
        system_id: int = 1,
        component_id: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER,
        heartbeat_rate_hz: float = 1.0,
        mav_type: int = mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
        signing: SigningConfig | None = None,
        record_path: str | Path | None = None,
        peer_system: int | None = None,
        peer_component: int = 0,
        peer_timeout_s: float = 3.0,
    ) -> None:
        self.endpoint = parse_url(url)
        self.peer_system = peer_system
        self.peer_component = peer_component
        self.peer_timeout_s = peer_timeout_s
        self._garbage = 0
        self._strangers = 0
        self._stranger_log_s = 0.0
        self.record_path = Path(record_path) if record_path is not None else None
        self._recorder: TlogWriter | None = None
        self.system_id = system_id
        self.component_id = component_id
        self.heartbeat_rate_hz = heartbeat_rate_hz
        self.mav_type = mav_type
        self.signing = signing
        self._writer = _Writer()
        self.mav = mavlink.MAVLink(self._writer, srcSystem=system_id, srcComponent=component_id)
        self.mav.robust_parsing = True
        self._transport: Transport | None = None
        self._listeners: list[tuple[frozenset[str] | None, Listener]] = []
        self._subscriptions: list[Subscription] = []
        self._background = BackgroundTasks()
        self._boot_s = time.monotonic()
        self._received = 0
        self._sent = 0
        self._bad_data = 0
        self._queue_dropped = 0
        self._bad_log_s = 0.0
        self._received_by_type: collections.Counter[str] = collections.Counter()
        if signing is not None:
            self._setup_signing(signing)

    @classmethod
    def from_config(cls, cfg: LinkConfig, record_path: str | Path | None = None) -> "MavlinkLink":
        """Build from a :class:`companion.config.LinkConfig` (reads the signing key file);
        ``record_path``: a ``.tlog`` to record into (e.g. in the run's output folder)."""
        signing = None
        if cfg.signing_key_path:
            signing = SigningConfig(key=load_signing_key(cfg.signing_key_path))
        return cls(
            cfg.url,
            system_id=cfg.system_id,
            component_id=cfg.component_id,
            heartbeat_rate_hz=cfg.heartbeat_rate_hz,
            signing=signing,
            record_path=record_path,
            peer_system=cfg.target_system,
            peer_component=cfg.target_component,
            peer_timeout_s=cfg.heartbeat_timeout_s,
        )

    # --- lifecycle -------------------------------------------------------------------

    async def __aenter__(self) -> "MavlinkLink":
        if self.record_path is not None:
            self._recorder = TlogWriter(self.record_path).__enter__()
        transport = make_transport(self.endpoint, self._on_bytes, self._on_stranger)
        try:
            await transport.__aenter__()
        except BaseException:
            self._close_recorder()
            raise
        self._transport = transport
        self._writer.transport = transport
        try:
            await self._background.open()
            if self.heartbeat_rate_hz > 0:
                self._background.start(self._heartbeat_loop(), name="heartbeat")
        except BaseException:
            await self._close_transport()
            raise
        log.info("MAVLink link up on %s as %d/%d%s", self.endpoint.url, self.system_id,
                 self.component_id, " (signed)" if self.signing else "")
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            await self._background.close()
        finally:
            for sub in list(self._subscriptions):
                sub._end()
            await self._close_transport()

    async def _close_transport(self) -> None:
        transport, self._transport = self._transport, None
        self._writer.transport = None
        try:
            if transport is not None:
                await transport.__aexit__(None, None, None)
        finally:
            self._close_recorder()

    def _close_recorder(self) -> None:
        recorder, self._recorder = self._recorder, None
        if recorder is not None:
            recorder.close()

    @property
    def transport(self) -> Transport:
        if self._transport is None:
            raise LinkError(f"{self.endpoint.url}: MAVLink link is not open")
        return self._transport

    @property
    def is_open(self) -> bool:
        return self._transport is not None

    # --- sending ---------------------------------------------------------------------

    def send(self, msg: Message) -> None:
        """Encode and send one message now (never blocks). Raises LinkError if closed."""
        if self._transport is None:
            raise LinkError(f"{self.endpoint.url}: cannot send {msg.get_type()}: link is not open")
        self.mav.send(msg)
        self._sent += 1

    def time_boot_ms(self) -> int:
        """Milliseconds since this link object was created (MAVLink ``time_boot_ms``)."""
        return int((time.monotonic() - self._boot_s) * 1000.0) & 0xFFFFFFFF

    async def _heartbeat_loop(self) -> None:
        period_s = 1.0 / self.heartbeat_rate_hz
        next_s = time.monotonic()
        while True:
            self.send(self.mav.heartbeat_encode(
                self.mav_type, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            ))
            next_s += period_s
            await asyncio.sleep(max(0.0, next_s - time.monotonic()))

    # --- receiving -------------------------------------------------------------------

    def _on_bytes(self, data: bytes) -> None:
        for msg in self._parse(data):
            self._dispatch(msg)

    def _parse(self, data: bytes) -> list[Message]:
        """The valid messages in ``data`` (malformed input counted and skipped)."""
        try:
            msgs = self.mav.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises plain exceptions on odd input
            self._count_bad(f"parser error: {exc}")
            self._reset_parser()
            return []
        good = []
        for msg in msgs:
            if isinstance(msg, mavlink.MAVLink_bad_data):
                self._count_bad(getattr(msg, "reason", "bad data"))
            elif not isinstance(msg, mavlink.MAVLink_unknown):
                good.append(msg)
        if self._transport is not None and self._transport.datagram and self.mav.buf_len():
            # A datagram holds whole messages; a tail is garbage and must not swallow the
            # start of the next datagram.
            self._count_bad("truncated message at the end of a datagram")
            self._reset_parser()
        return good

    def _is_peer_ids(self, system_id: int, component_id: int) -> bool:
        return ((self.peer_system is None or system_id == self.peer_system)
                and (self.peer_component == 0 or component_id == self.peer_component))

    def _on_stranger(self, data: bytes, addr: Any) -> None:
        """A ``udpin`` datagram from another address than the peer: it becomes the peer when
        it carries a valid (signed, with signing on) packet from the autopilot and the old
        peer has been silent for ``peer_timeout_s``; else it is counted and dropped. The
        checks run cheapest first, so a flood costs a few byte reads per datagram."""
        transport = self._transport
        assert isinstance(transport, UdpTransport)
        ids = first_packet_ids(data)
        if ids is None:
            self._garbage += 1
            self._log_stranger(addr, "not MAVLink")
            return
        if not self._is_peer_ids(*ids):
            self._strangers += 1
            self._log_stranger(addr, f"from system {ids[0]}/{ids[1]}, not the autopilot")
            return
        if transport.peer is not None and transport.peer_silent_s() < self.peer_timeout_s:
            self._strangers += 1
            self._log_stranger(addr, "the link is locked to its peer, which is alive")
            return
        msgs = self._parse(data)
        if not any(self._is_peer_ids(m.get_srcSystem(), m.get_srcComponent())
                   and (self.signing is None or m.get_signed()) for m in msgs):
            self._strangers += 1
            self._log_stranger(addr, "no valid packet from the autopilot" + (" (signed)" if self.signing else ""))
            return
        transport.set_peer(addr)
        for msg in msgs:
            self._dispatch(msg)

    def _log_stranger(self, addr: Any, why: str) -> None:
        now = time.monotonic()
        if now - self._stranger_log_s > 5.0:
            self._stranger_log_s = now
            log.warning("%s: ignored a datagram from %s:%s (%s); %d strangers, %d garbage so far",
                        self.endpoint.url, addr[0], addr[1], why, self._strangers, self._garbage)

    def _reset_parser(self) -> None:
        self.mav.buf = bytearray()
        self.mav.buf_index = 0
        self.mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def _count_bad(self, reason: str) -> None:
        self._bad_data += 1
        now = time.monotonic()
        if now - self._bad_log_s > 5.0:
            self._bad_log_s = now
            log.warning("%s: discarded malformed MAVLink input (%s; %d so far)",
                        self.endpoint.url, reason, self._bad_data)

    def _dispatch(self, msg: Message) -> None:
        self._received += 1
        if self._recorder is not None:
            self._recorder.write(bytes(msg.get_msgbuf()))
        mtype = msg.get_type()
        self._received_by_type[mtype] += 1
        for types, callback in list(self._listeners):
            if types is None or mtype in types:
                try:
                    callback(msg)
                except Exception:
                    log.exception("MAVLink listener %r failed on %s", callback, mtype)
        for sub in self._subscriptions:
            if sub.msg_types is None or mtype in sub.msg_types:
                sub._offer(msg)

    def add_listener(self, callback: Listener, msg_types: Iterable[str] | None = None) -> Callable[[], None]:
        """Call ``callback(msg)`` synchronously for each matching message; returns a remover.

        Listeners run inside the receive path: keep them short and non-blocking.
        """
        entry = (frozenset(msg_types) if msg_types is not None else None, callback)
        self._listeners.append(entry)

        def remove() -> None:
            if entry in self._listeners:
                self._listeners.remove(entry)

        return remove

    def subscribe(self, *msg_types: str, maxsize: int = DEFAULT_QUEUE_SIZE) -> Subscription:
        """A bounded async iterator over messages of these types (all types if none given)."""
        sub = Subscription(self, frozenset(msg_types) if msg_types else None, maxsize)
        self._subscriptions.append(sub)
        return sub

    def _remove_subscription(self, sub: Subscription) -> None:
        if sub in self._subscriptions:
            self._subscriptions.remove(sub)

    async def wait_message(
        self,
        msg_type: str | Iterable[str],
        timeout_s: float,
        predicate: Callable[[Message], bool] | None = None,
    ) -> Message:
        """The next message of ``msg_type`` satisfying ``predicate``.

        Raises :class:`TimeoutError` after ``timeout_s`` seconds.
        """
        types = (msg_type,) if isinstance(msg_type, str) else tuple(msg_type)
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Message] = loop.create_future()

        def on_msg(msg: Message) -> None:
            if not fut.done() and (predicate is None or predicate(msg)):
                fut.set_result(msg)

        remove = self.add_listener(on_msg, types)
        try:
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            remove()

    # --- signing and statistics ------------------------------------------------------

    def _setup_signing(self, signing: SigningConfig) -> None:
        s = self.mav.signing
        s.secret_key = signing.key
        s.link_id = signing.link_id
        s.timestamp = signing_timestamp_now()
        s.sign_outgoing = True
        allowed = signing.allow_unsigned_ids
        s.allow_unsigned_callback = lambda _mav, msg_id: msg_id in allowed

    @property
    def stats(self) -> LinkStats:
        return LinkStats(
            messages_received=self._received,
            messages_sent=self._sent,
            bad_data=self._bad_data,
            send_dropped=self._transport.send_dropped if self._transport else 0,
            queue_dropped=self._queue_dropped,
            signature_rejected=self.mav.signing.reject_count + self.mav.signing.badsig_count,
            garbage_dropped=self._garbage,
            strangers_dropped=self._strangers,
            peer=(f"{peer[0]}:{peer[1]}" if (peer := getattr(self._transport, "peer", None)) is not None else None),
            peer_changes=getattr(self._transport, "peer_changes", 0),
        )

    def received_count(self, msg_type: str) -> int:
        """How many messages of ``msg_type`` arrived since the link opened."""
        return self._received_by_type[msg_type]
