"""Frames of any :class:`FrameSource` as an asyncio stream that never falls behind.

A source's ``read()`` blocks (a camera waits for its next frame, the simulator renders), so a
dedicated reader thread calls it and hands frames to the event loop. The hand-over queue is
bounded (``queue_size``, default 1): when the consumer is slower than the camera the *oldest*
waiting frame is dropped and counted, so perception always works on the newest frame and
never on a backlog. Errors from the source end the stream and are raised to the consumer.

    async with FrameStream(source, rate_hz=15.0) as frames:
        async for frame in frames:
            ...
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import AsyncIterator
from types import TracebackType

from companion.sources.base import FrameSource
from semmap.errors import FrameError
from semmap.types import Frame

log = logging.getLogger(__name__)

_END = object()


class FrameStream:
    """Async iterator over a source's frames with drop-oldest back-pressure.

    ``rate_hz`` paces the reads (a simulated or recorded source otherwise runs flat out; a
    live camera paces itself, leave it None). ``dropped_frames`` counts frames discarded
    because the consumer was busy; ``source.dropped_frames`` counts the source's own bad
    frames. The source is opened on entry and closed on exit.
    """

    def __init__(self, source: FrameSource, queue_size: int = 1, rate_hz: float | None = None) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1 (got {queue_size})")
        if rate_hz is not None and rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0 (got {rate_hz})")
        self.source = source
        self.queue_size = queue_size
        self.rate_hz = rate_hz
        self.dropped_frames = 0
        self.frames_delivered = 0
        self._queue: asyncio.Queue[object] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    async def __aenter__(self) -> FrameStream:
        await asyncio.to_thread(self.source.open)
        self._loop = asyncio.get_running_loop()
        # One extra slot for the end marker, so the end is never dropped.
        self._queue = asyncio.Queue(maxsize=self.queue_size + 1)
        self._stop.clear()
        self._thread = threading.Thread(target=self._reader, name="frame-reader", daemon=True)
        self._thread.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Stop the reader thread and close the source. Idempotent."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            await asyncio.to_thread(thread.join)
            await asyncio.to_thread(self.source.close)

    def __aiter__(self) -> AsyncIterator[Frame]:
        return self

    async def __anext__(self) -> Frame:
        if self._queue is None:
            raise RuntimeError("FrameStream used outside 'async with'")
        item = await self._queue.get()
        if item is _END:
            self._queue.put_nowait(_END)  # stay ended for later calls
            if self._error is not None:
                raise self._error
            raise StopAsyncIteration
        self.frames_delivered += 1
        assert isinstance(item, Frame)
        return item

    # --- the reader thread --------------------------------------------------------------

    def _reader(self) -> None:
        period = 1.0 / self.rate_hz if self.rate_hz else 0.0
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                if period:
                    delay = next_t - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        break
                    next_t = max(next_t + period, time.monotonic() - period)
                frame = self.source.read()
                if frame is None:
                    break
                self._deliver(frame)
        except FrameError as exc:
            self._error = exc
            log.error("frame source failed: %s", exc)
        except Exception as exc:  # a bug in a source must still end the stream visibly
            self._error = FrameError(f"frame source crashed: {exc!r}")
            self._error.__cause__ = exc
            log.exception("frame source crashed")
        finally:
            self._deliver(_END)

    def _deliver(self, item: object) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # the loop closed while we were reading
            loop.call_soon_threadsafe(self._put_newest, item)

    def _put_newest(self, item: object) -> None:
        """On the loop: enqueue, dropping the oldest frame if the consumer is behind."""
        q = self._queue
        assert q is not None
        if item is not _END:
            while q.qsize() >= self.queue_size:
                old = q.get_nowait()
                if old is _END:  # never drop the end marker (cannot happen before it)
                    q.put_nowait(old)
                    return
                self.dropped_frames += 1
                if self.dropped_frames in (1, 10, 100) or self.dropped_frames % 1000 == 0:
                    log.warning("consumer is slower than the camera: %d frames dropped", self.dropped_frames)
        q.put_nowait(item)
