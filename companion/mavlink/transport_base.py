"""The byte channel every MAVLink transport is: open/close as an async context manager,
received bytes handed to a callback, sends that never block and count what they drop."""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable
from types import TracebackType

from companion.errors import LinkError
from companion.mavlink.urls import Endpoint

log = logging.getLogger(__name__)

BytesCallback = Callable[[bytes], None]


class Transport(abc.ABC):
    """One open byte channel to the peer."""

    #: True when each received chunk is a whole datagram (no message spans two chunks).
    datagram: bool = False

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        self.endpoint = endpoint
        self._on_bytes = on_bytes
        self.bytes_sent = 0
        self.bytes_received = 0
        self.send_dropped = 0

    async def __aenter__(self) -> "Transport":
        try:
            await self._open()
        except OSError as exc:
            raise LinkError(f"{self.endpoint.url}: cannot open: {exc.strerror or exc}") from exc
        log.info("link transport open: %s", self.describe())
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self._close()
        log.info("link transport closed: %s", self.endpoint.url)

    @abc.abstractmethod
    async def _open(self) -> None: ...

    @abc.abstractmethod
    async def _close(self) -> None: ...

    @abc.abstractmethod
    def send(self, data: bytes) -> bool:
        """Queue ``data`` for sending; False (and counted) if it had to be dropped."""

    @property
    @abc.abstractmethod
    def connected(self) -> bool:
        """True when a peer is known/connected, i.e. :meth:`send` can deliver."""

    def describe(self) -> str:
        return self.endpoint.url

    def _deliver(self, data: bytes) -> None:
        self.bytes_received += len(data)
        self._on_bytes(data)

    def _drop(self, reason: str, n: int, quiet: bool = False) -> bool:
        self.send_dropped += 1
        if quiet:
            log.debug("%s: dropped %d outgoing bytes (%s)", self.endpoint.url, n, reason)
        elif self.send_dropped == 1 or self.send_dropped % 100 == 0:
            log.warning("%s: dropped outgoing bytes (%s; %d drops so far)",
                        self.endpoint.url, reason, self.send_dropped)
        return False
