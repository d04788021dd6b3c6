"""The mock autopilot's UDP endpoint, with the link faults tests inject.

One socket bound to the local port sends every packet to the configured remotes and to any
address that sent us something in the last :data:`PEER_TIMEOUT_S` (how PX4 learns a partner).
Each incoming datagram is parsed on its own: a UDP datagram carries whole MAVLink packets, so a
truncated or corrupt packet must not swallow the start of the next datagram.
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import SimulationError

log = logging.getLogger(__name__)

PEER_TIMEOUT_S = 10.0
#: Seconds between 1970-01-01 and the MAVLink signing epoch (2015-01-01 00:00:00 UTC).
_SIGNING_EPOCH_UNIX_S = 1420070400

Address = tuple[str, int]


@dataclass
class Faults:
    """Fault injection, changeable at any time while the mock runs."""

    #: Cut the link both ways (nothing sent, everything received is discarded).
    drop_link: bool = False
    drop_outgoing: bool = False
    drop_incoming: bool = False
    #: Extra one-way latency added to everything the mock sends (seconds).
    delay_s: float = 0.0
    #: Commands (MAV_CMD ids) answered with MAV_RESULT_DENIED.
    reject_commands: set[int] = field(default_factory=set)
    #: Commands (MAV_CMD ids) never answered (the client times out).
    ignore_commands: set[int] = field(default_factory=set)
    #: Probability per outgoing byte of being replaced by a random byte.
    corrupt_bytes_rate: float = 0.0
    #: Upload of this mission item index is rejected with MAV_MISSION_DENIED.
    reject_mission_seq: int | None = None
    #: Pre-arm checks fail (SYS_STATUS health bit cleared, arming denied).
    prearm_fail: bool = False


def sign_with(mav: mavlink.MAVLink, key: bytes, link_id: int = 0) -> None:
    """Sign every packet ``mav`` encodes with ``key``, and accept only signed packets when
    it parses (MAVLink 2 signing, 32-byte key)."""
    if len(key) != 32:
        raise SimulationError(f"MAVLink signing key must be 32 bytes (got {len(key)})")
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.timestamp = int((time.time() - _SIGNING_EPOCH_UNIX_S) * 100_000)
    mav.signing.sign_outgoing = True


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpEndpoint) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self._owner._on_datagram(data, (str(addr[0]), int(addr[1])))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when nobody listens on a remote port yet: normal for UDP.
        log.debug("mock autopilot socket error: %s", exc)


class UdpEndpoint:
    """MAVLink 2 over one UDP socket. ``on_message(msg)`` gets every parsed message."""

    def __init__(self, mav: mavlink.MAVLink, host: str, local_port: int,
                 remotes: list[Address], faults: Faults,
                 on_message: Callable[[Any], None], seed: int = 0) -> None:
        self._mav = mav
        self.host = host
        self._requested_port = local_port
        self.remotes = list(remotes)
        self._learned: dict[Address, float] = {}
        self.faults = faults
        self._on_message = on_message
        self._rng = random.Random(seed)
        self._transport: asyncio.DatagramTransport | None = None
        self.bad_packets = 0
        #: With signing required (:meth:`require_signed`): the one parser that checks signatures.
        self._signed_parser: mavlink.MAVLink | None = None
        self._unsigned_from: set[Address] = set()
        self.unsigned_rejected = 0

    def require_signed(self, key: bytes, unsigned_from: tuple[Address, ...] = ()) -> None:
        """Accept only packets signed with ``key`` (PX4 with ``MAV_SIGN_CFG``), except from
        the ``unsigned_from`` addresses (PX4 exempts its USB link the same way). One parser
        keeps the signature timestamps, so a replayed packet is refused too."""
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        sign_with(parser, key)
        self._signed_parser = parser
        self._unsigned_from = set(unsigned_from)

    def _parser_for(self, addr: Address) -> mavlink.MAVLink:
        if self._signed_parser is None or addr in self._unsigned_from:
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            return parser
        p = self._signed_parser
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        return p

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _Protocol(self), local_addr=(self.host, self._requested_port))
        except OSError as exc:
            raise SimulationError(
                f"mock autopilot cannot bind UDP {self.host}:{self._requested_port}: {exc}"
            ) from exc
        self._transport = transport  # type: ignore[assignment]

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    @property
    def is_open(self) -> bool:
        return self._transport is not None

    @property
    def local_port(self) -> int:
        if self._transport is None:
            return self._requested_port
        return int(self._transport.get_extra_info("sockname")[1])

    def targets(self) -> list[Address]:
        """Where packets go: configured remotes, then recently heard peers."""
        now = time.monotonic()
        for addr, seen in list(self._learned.items()):
            if now - seen > PEER_TIMEOUT_S:
                del self._learned[addr]
        return self.remotes + [a for a in self._learned if a not in self.remotes]

    # --- sending -------------------------------------------------------------------------

    def send(self, msg: Any) -> None:
        """Encode a pymavlink message (next sequence number) and send it to every target."""
        if self._transport is None:
            return
        buf = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        self.send_raw(buf)

    def send_raw(self, data: bytes) -> None:
        """Send bytes as they are (subject to the faults) to every target."""
        for addr in self.targets():
            self._sendto(data, addr)

    def random_bytes(self, n: int) -> bytes:
        return bytes(self._rng.getrandbits(8) for _ in range(max(0, n)))

    def _sendto(self, data: bytes, addr: Address) -> None:
        f = self.faults
        if f.drop_link or f.drop_outgoing or self._transport is None:
            return
        if f.corrupt_bytes_rate > 0:
            b = bytearray(data)
            for i in range(len(b)):
                if self._rng.random() < f.corrupt_bytes_rate:
                    b[i] = self._rng.getrandbits(8)
            data = bytes(b)
        if f.delay_s > 0:
            asyncio.get_running_loop().call_later(f.delay_s, self._sendto_now, data, addr)
        else:
            self._sendto_now(data, addr)

    def _sendto_now(self, data: bytes, addr: Address) -> None:
        if self._transport is not None:
            try:
                self._transport.sendto(data, addr)
            except OSError as exc:
                log.debug("send to %s:%d failed: %s", addr[0], addr[1], exc)

    # --- receiving -----------------------------------------------------------------------

    def _on_datagram(self, data: bytes, addr: Address) -> None:
        if self.faults.drop_link or self.faults.drop_incoming:
            return
        parser = self._parser_for(addr)
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises plain MAVError/struct errors on junk
            self.bad_packets += 1
            log.debug("unparseable datagram from %s:%d: %s", addr[0], addr[1], exc)
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.bad_packets += 1
                if "signature" in str(getattr(msg, "reason", "")).lower():
                    self.unsigned_rejected += 1
                continue
            self._learned[addr] = time.monotonic()
            try:
                self._on_message(msg)
            except Exception:  # a bad field must not take the autopilot down
                self.bad_packets += 1
                log.exception("error handling %s from %s:%d", msg.get_type(), *addr)
