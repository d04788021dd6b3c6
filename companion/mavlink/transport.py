"""Byte transports for the MAVLink link, driven by the asyncio event loop.

Each transport is an async context manager. Received bytes are handed to the ``on_bytes``
callback from inside the event loop as they arrive (one call per datagram or per read);
:meth:`Transport.send` never blocks and never raises on a transient network condition: a
datagram that cannot go out is dropped and counted, because MAVLink is a lossy protocol and a
stalled sender is worse than a lost setpoint.

* UDP in (``udpin://``): bound to a local port, replies to its peer: the first address whose
  datagram the link accepted (``on_stranger``: a valid MAVLink packet from the autopilot).
  Datagrams from any other address go to ``on_stranger`` and are dropped unless the link
  accepts them; the peer changes only once it has been silent for ``peer_timeout_s``.
* UDP out (``udpout://``): sends to a fixed address from an ephemeral port.
* TCP client (``tcp://``): reconnects with back-off while open.
* TCP server (``tcpin://``): one client at a time; a new client replaces the old one.
* Serial (``serial://``): pyserial opens and configures the device; reads are driven by
  ``loop.add_reader`` on its file descriptor, writes go through a small bounded buffer.
* Replay (``tlog://``): a recorded telemetry log delivered packet by packet with its recorded
  timing (scaled by ``?speed=``); a read-only link, what we send is dropped
  (:mod:`companion.mavlink.replay`).

The interface they share is :class:`~companion.mavlink.transport_base.Transport`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Callable
from typing import Any

from companion.background import BackgroundTasks
from companion.errors import LinkError
from companion.mavlink.replay import ReplayTransport
from companion.mavlink.transport_base import BytesCallback, Transport
from companion.mavlink.urls import Endpoint, EndpointKind

log = logging.getLogger(__name__)

#: ``(datagram, source address)`` for a datagram that is not from the UDP peer.
StrangerCallback = Callable[[bytes, Any], None]

#: A stream transport drops outgoing bytes rather than buffer more than this.
MAX_WRITE_BUFFER_BYTES = 64 * 1024
#: ``udpin`` reads at most this many datagrams per wake-up before the loop runs its timers.
UDP_READ_BATCH = 64
#: ``udpin`` socket receive buffer (the kernel caps it at ``net.core.rmem_max``).
UDP_RECEIVE_BUFFER_BYTES = 1 << 20
TCP_RECONNECT_MIN_S = 0.2
TCP_RECONNECT_MAX_S = 2.0


# --- UDP ---------------------------------------------------------------------------------

def _bound_udp_socket(host: str, port: int) -> socket.socket:
    """A non-blocking UDP socket bound to ``host:port`` with a receive buffer that absorbs a
    burst while the event loop is busy."""
    family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)[0]
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER_BYTES)
        sock.bind(addr)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


class _DatagramProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: "UdpTransport") -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self._owner._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port-unreachable and friends: the peer is not up yet. MAVLink carries on.
        log.debug("%s: socket error %s", self._owner.endpoint.url, exc)


class UdpTransport(Transport):
    """``udpin://`` (bind, reply to the locked peer) or ``udpout://`` (fixed peer).

    ``on_stranger``: called for each ``udpin`` datagram not from the peer (the link decides
    whether it may become the peer, see :meth:`set_peer`); without it strangers are dropped.
    """

    datagram = True

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback,
                 on_stranger: StrangerCallback | None = None) -> None:
        super().__init__(endpoint, on_bytes)
        self._transport: asyncio.DatagramTransport | None = None
        #: ``udpin``: our own non-blocking socket, drained in batches (:meth:`_drain`).
        self._sock: socket.socket | None = None
        self._peer: Any = None
        self._on_stranger = on_stranger
        #: When the peer last sent a datagram (monotonic s).
        self.peer_seen_s = -float("inf")
        self.peer_changes = 0

    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        ep = self.endpoint
        if ep.kind is EndpointKind.UDP_IN:
            self._sock = await asyncio.to_thread(_bound_udp_socket, ep.host, ep.port)
            loop.add_reader(self._sock.fileno(), self._drain)
        else:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _DatagramProtocol(self), remote_addr=(ep.host, ep.port)
            )
            self._peer = (ep.host, ep.port)
            self._transport = transport

    async def _close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        if self._sock is not None:
            asyncio.get_running_loop().remove_reader(self._sock.fileno())
            self._sock.close()
            self._sock = None

    def _drain(self) -> None:
        """Read what is queued (up to a batch, so timers run between batches): one wake-up
        per batch rather than per datagram keeps a flood from starving the setpoint task."""
        sock = self._sock
        for _ in range(UDP_READ_BATCH):
            if sock is None:
                return
            try:
                data, addr = sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                # ICMP port-unreachable and friends: the peer is not up yet. MAVLink carries on.
                log.debug("%s: socket error %s", self.endpoint.url, exc)
                return
            self._on_datagram(data, addr)
            sock = self._sock  # a callback may have closed the link

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound (host, port); useful when the URL asked for port 0."""
        if self._sock is not None:
            sockname = self._sock.getsockname()
        elif self._transport is not None:
            sockname = self._transport.get_extra_info("sockname")
        else:
            raise LinkError(f"{self.endpoint.url}: transport is not open")
        return str(sockname[0]), int(sockname[1])

    @property
    def peer(self) -> Any:
        return self._peer

    @property
    def connected(self) -> bool:
        return (self._transport is not None or self._sock is not None) and self._peer is not None

    def describe(self) -> str:
        if self._transport is None and self._sock is None:
            return self.endpoint.url
        host, port = self.local_address
        return f"{self.endpoint.url} (local {host}:{port})"

    def _on_datagram(self, data: bytes, addr: Any) -> None:
        if addr == self._peer:
            self.peer_seen_s = time.monotonic()
            self._deliver(data)
        elif self.endpoint.kind is EndpointKind.UDP_OUT:
            self._deliver(data)
        elif self._on_stranger is not None:
            self._on_stranger(data, addr)

    def peer_silent_s(self) -> float:
        """Seconds since the peer last sent (infinite when there is no peer)."""
        return time.monotonic() - self.peer_seen_s

    def set_peer(self, addr: Any) -> None:
        """Reply to ``addr`` from now on (``udpin``; the link accepted its datagram)."""
        if addr != self._peer:
            if self._peer is None:
                log.info("%s: peer is %s:%s", self.endpoint.url, addr[0], addr[1])
            else:
                log.warning("%s: peer changed from %s:%s (silent %.1f s) to %s:%s", self.endpoint.url,
                            self._peer[0], self._peer[1], self.peer_silent_s(), addr[0], addr[1])
            self._peer = addr
            self.peer_changes += 1
        self.peer_seen_s = time.monotonic()

    def send(self, data: bytes) -> bool:
        if self._transport is None and self._sock is None:
            return self._drop("transport closed", len(data))
        if self._peer is None:
            # Normal until the autopilot's first datagram tells us where it is.
            return self._drop("no peer has sent to us yet", len(data), quiet=True)
        if self._sock is not None:
            try:
                self._sock.sendto(data, self._peer)
            except (BlockingIOError, InterruptedError):
                return self._drop("socket buffer full", len(data))
            except OSError as exc:
                return self._drop(f"send failed: {exc.strerror or exc}", len(data))
            self.bytes_sent += len(data)
            return True
        assert self._transport is not None
        # Selector datagram transports buffer when the socket would block (not in typeshed).
        buffered = getattr(self._transport, "get_write_buffer_size", lambda: 0)()
        if buffered > MAX_WRITE_BUFFER_BYTES:
            return self._drop("socket buffer full", len(data))
        self._transport.sendto(data)
        self.bytes_sent += len(data)
        return True


# --- TCP ---------------------------------------------------------------------------------

class _StreamProtocol(asyncio.Protocol):
    def __init__(self, owner: "_TcpBase") -> None:
        self._owner = owner
        self.transport: asyncio.Transport | None = None
        self.closed = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self._owner._on_connected(self)

    def data_received(self, data: bytes) -> None:
        self._owner._deliver(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._owner._on_disconnected(self, exc)
        if not self.closed.done():
            self.closed.set_result(None)


class _TcpBase(Transport):
    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        super().__init__(endpoint, on_bytes)
        self._proto: _StreamProtocol | None = None

    def _on_connected(self, proto: _StreamProtocol) -> None:
        if self._proto is not None and self._proto.transport is not None:
            log.info("%s: a new client replaces the previous one", self.endpoint.url)
            self._proto.transport.close()
        self._proto = proto
        peer = proto.transport.get_extra_info("peername") if proto.transport else None
        log.info("%s: connected (%s)", self.endpoint.url, peer)

    def _on_disconnected(self, proto: _StreamProtocol, exc: Exception | None) -> None:
        if self._proto is proto:
            self._proto = None
            log.warning("%s: connection lost%s", self.endpoint.url, f" ({exc})" if exc else "")

    @property
    def connected(self) -> bool:
        return self._proto is not None and self._proto.transport is not None

    def send(self, data: bytes) -> bool:
        proto = self._proto
        if proto is None or proto.transport is None or proto.transport.is_closing():
            return self._drop("not connected", len(data))
        if proto.transport.get_write_buffer_size() > MAX_WRITE_BUFFER_BYTES:
            return self._drop("peer is not reading", len(data))
        proto.transport.write(data)
        self.bytes_sent += len(data)
        return True


class TcpClientTransport(_TcpBase):
    """``tcp://host:port``: connects, and reconnects with back-off while open."""

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        super().__init__(endpoint, on_bytes)
        self._background = BackgroundTasks()

    async def _open(self) -> None:
        await self._background.open()
        self._background.start(self._connect_loop(), name=f"tcp {self.endpoint.url}")

    async def _close(self) -> None:
        # The socket closes before the loop is cancelled; its connection_lost runs only at
        # the next await, by when the loop is cancelled and does not reconnect.
        if self._proto is not None and self._proto.transport is not None:
            self._proto.transport.close()
        await self._background.close()

    async def _connect_loop(self) -> None:
        loop = asyncio.get_running_loop()
        delay_s = TCP_RECONNECT_MIN_S
        while True:
            try:
                _, proto = await loop.create_connection(
                    lambda: _StreamProtocol(self), self.endpoint.host, self.endpoint.port
                )
            except OSError as exc:
                log.debug("%s: connect failed (%s); retrying in %.1f s",
                          self.endpoint.url, exc.strerror or exc, delay_s)
                await asyncio.sleep(delay_s)
                delay_s = min(delay_s * 2.0, TCP_RECONNECT_MAX_S)
                continue
            delay_s = TCP_RECONNECT_MIN_S
            await proto.closed


class TcpServerTransport(_TcpBase):
    """``tcpin://host:port``: accepts clients; the newest one is the peer."""

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        super().__init__(endpoint, on_bytes)
        self._server: asyncio.Server | None = None

    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: _StreamProtocol(self), self.endpoint.host, self.endpoint.port
        )

    async def _close(self) -> None:
        if self._proto is not None and self._proto.transport is not None:
            self._proto.transport.close()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None

    @property
    def local_address(self) -> tuple[str, int]:
        if self._server is None or not self._server.sockets:
            raise LinkError(f"{self.endpoint.url}: transport is not open")
        sockname = self._server.sockets[0].getsockname()
        return str(sockname[0]), int(sockname[1])


# --- serial ------------------------------------------------------------------------------

class SerialTransport(Transport):
    """``serial:///dev/ttyX:baud``: pyserial opens the port; the event loop reads its fd."""

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        super().__init__(endpoint, on_bytes)
        self._serial: Any = None
        self._fd = -1
        self._pending = bytearray()

    async def _open(self) -> None:
        try:
            import serial  # pyserial: a runtime dependency, imported where serial is used
        except ImportError as exc:
            raise LinkError(f"{self.endpoint.url}: pyserial is not installed") from exc
        try:
            self._serial = serial.Serial(
                self.endpoint.device, self.endpoint.baud, timeout=0, write_timeout=0,
                exclusive=True,
            )
        except (serial.SerialException, ValueError) as exc:
            raise LinkError(f"{self.endpoint.url}: cannot open serial device: {exc}") from exc
        self._fd = self._serial.fileno()
        os.set_blocking(self._fd, False)
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    async def _close(self) -> None:
        if self._serial is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(self._fd)
        loop.remove_writer(self._fd)
        with contextlib.suppress(OSError):
            self._serial.close()
        self._serial = None
        self._fd = -1

    @property
    def connected(self) -> bool:
        return self._serial is not None

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            # A USB adapter unplugged: stop reading; the heartbeat watchdog reports link loss.
            log.error("%s: read failed (%s); serial link is down", self.endpoint.url, exc)
            asyncio.get_running_loop().remove_reader(self._fd)
            return
        if data:
            self._deliver(data)

    def send(self, data: bytes) -> bool:
        if self._serial is None:
            return self._drop("port closed", len(data))
        if len(self._pending) + len(data) > MAX_WRITE_BUFFER_BYTES:
            return self._drop("serial output buffer full", len(data))
        was_empty = not self._pending
        self._pending += data
        if was_empty:
            self._flush()
        self.bytes_sent += len(data)
        return True

    def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            n = os.write(self._fd, self._pending)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            log.error("%s: write failed (%s)", self.endpoint.url, exc)
            self._pending.clear()
            loop.remove_writer(self._fd)
            return
        del self._pending[:n]
        if self._pending:
            loop.add_writer(self._fd, self._flush)
        else:
            loop.remove_writer(self._fd)


def make_transport(endpoint: Endpoint, on_bytes: BytesCallback,
                   on_stranger: StrangerCallback | None = None) -> Transport:
    """The transport for an endpoint (not yet open: use it with ``async with``);
    ``on_stranger``: see :class:`UdpTransport`."""
    if endpoint.kind in (EndpointKind.UDP_IN, EndpointKind.UDP_OUT):
        return UdpTransport(endpoint, on_bytes, on_stranger)
    if endpoint.kind is EndpointKind.TCP_CLIENT:
        return TcpClientTransport(endpoint, on_bytes)
    if endpoint.kind is EndpointKind.TCP_SERVER:
        return TcpServerTransport(endpoint, on_bytes)
    if endpoint.kind is EndpointKind.REPLAY:
        return ReplayTransport(endpoint, on_bytes)
    return SerialTransport(endpoint, on_bytes)
