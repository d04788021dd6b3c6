"""Replay (``tlog://``): a recorded telemetry log fed into the link as if it arrived live."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Iterator
from pathlib import Path

from companion.background import BackgroundTasks
from companion.errors import DataError, LinkError
from companion.mavlink.tlog import TlogRecord, iter_tlog
from companion.mavlink.transport_base import BytesCallback, Transport
from companion.mavlink.urls import Endpoint

log = logging.getLogger(__name__)


class ReplayTransport(Transport):
    """``tlog:///path.tlog``: replays a telemetry log; :attr:`finished` is set at its end."""

    datagram = True  # every delivery is one whole packet

    def __init__(self, endpoint: Endpoint, on_bytes: BytesCallback) -> None:
        super().__init__(endpoint, on_bytes)
        self.finished = asyncio.Event()
        self.packets = 0
        self._background = BackgroundTasks()
        self._records: Iterator[TlogRecord] | None = None

    async def _open(self) -> None:
        path = Path(self.endpoint.device)
        if not await asyncio.to_thread(path.is_file):
            raise LinkError(f"{self.endpoint.url}: no such telemetry log {path}")
        self._records = iter_tlog(path)
        await self._background.open()
        self._background.start(self._replay(), name=f"replay {path.name}")

    async def _close(self) -> None:
        await self._background.close()

    @property
    def connected(self) -> bool:
        return self._background.running and not self.finished.is_set()

    def send(self, data: bytes) -> bool:
        return self._drop("replay is read-only", len(data), quiet=True)

    async def _replay(self) -> None:
        assert self._records is not None
        speed = self.endpoint.speed
        t0_log: float | None = None
        t0 = time.monotonic()
        try:
            for rec in self._records:
                if t0_log is None:
                    t0_log = rec.stamp_s
                if speed > 0:
                    due = t0 + (rec.stamp_s - t0_log) / speed
                    delay = due - time.monotonic()
                    if delay > 0:
                        await asyncio.sleep(delay)
                elif self.packets % 100 == 0:
                    await asyncio.sleep(0)  # as fast as possible, but let the loop breathe
                self.packets += 1
                self._deliver(rec.packet)
        except DataError as exc:
            log.error("%s: replay stopped: %s", self.endpoint.url, exc)
        finally:
            self.finished.set()
        log.info("%s: replay finished after %d packets", self.endpoint.url, self.packets)
