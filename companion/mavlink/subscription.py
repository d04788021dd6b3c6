"""A bounded queue of received MAVLink messages (:meth:`MavlinkLink.subscribe`)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, TypeAlias

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError

if TYPE_CHECKING:
    from companion.mavlink.link import MavlinkLink

log = logging.getLogger(__name__)

Message: TypeAlias = mavlink.MAVLink_message


class Subscription:
    """A bounded queue of received messages, as an async iterator and context manager.

    When full, the oldest message is dropped (the consumer wants the newest) and the drop is
    logged on the first occurrence and every 100th after. When the link closes, a waiting
    :meth:`get` raises :class:`LinkError` and ``async for`` ends.
    """

    def __init__(self, link: "MavlinkLink", msg_types: frozenset[str] | None, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"subscription queue size must be >= 1 (got {maxsize})")
        self._link = link
        self.msg_types = msg_types
        # One extra slot so the end-of-link marker always fits.
        self._queue: asyncio.Queue[Message | None] = asyncio.Queue(maxsize + 1)
        self._maxsize = maxsize
        self.dropped = 0
        self._closed = False
        self._link_closed = False

    def _offer(self, msg: Message) -> None:
        if self._queue.qsize() >= self._maxsize:
            self._queue.get_nowait()
            self.dropped += 1
            self._link._queue_dropped += 1
            if self.dropped == 1 or self.dropped % 100 == 0:
                log.warning("slow subscriber to %s: dropped %d old messages",
                            sorted(self.msg_types) if self.msg_types else "all", self.dropped)
        self._queue.put_nowait(msg)

    def _end(self) -> None:
        """The link closed: wake the consumer."""
        self._link_closed = True
        self._queue.put_nowait(None)
        self.close()

    async def _next(self) -> Message | None:
        msg = await self._queue.get()
        if msg is None:
            self._queue.put_nowait(None)  # every later call sees the end too
        return msg

    async def get(self, timeout_s: float | None = None) -> Message:
        """The next message; raises :class:`TimeoutError` after ``timeout_s`` seconds and
        :class:`LinkError` once the link has closed."""
        if timeout_s is None:
            msg = await self._next()
        else:
            async with asyncio.timeout(timeout_s):
                msg = await self._next()
        if msg is None:
            raise LinkError(f"{self._link.endpoint.url}: link closed")
        return msg

    def get_nowait(self) -> Message | None:
        """The next queued message, or None if there is none (or the link closed)."""
        try:
            msg = self._queue.get_nowait()
        except asyncio.QueueEmpty:
            return None
        if msg is None:
            self._queue.put_nowait(None)
        return msg

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._link._remove_subscription(self)

    async def __aenter__(self) -> "Subscription":
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def __aiter__(self) -> AsyncIterator[Message]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Message]:
        try:
            while True:
                msg = await self._next()
                if msg is None:
                    return
                yield msg
        finally:
            self.close()
