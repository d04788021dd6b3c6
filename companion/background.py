"""The loops a long-lived part runs while it is open (a setpoint stream, a heartbeat, a feed).

A part opens its :class:`BackgroundTasks` in ``__aenter__``, starts its loops with
:meth:`BackgroundTasks.start`, and closes it in ``__aexit__``. They run in an
:class:`asyncio.TaskGroup`: a loop that fails cancels the task that opened the part, so a part
whose loop died is never left looking alive. The group is left with ``(None, None, None)``, so
an exception from the owner's own ``async with`` body is not wrapped into an ExceptionGroup.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any


class BackgroundTasks:
    """The background loops of one part, from :meth:`open` to :meth:`close`."""

    def __init__(self) -> None:
        self._tg: asyncio.TaskGroup | None = None
        self._tasks: list[asyncio.Task[Any]] = []

    @property
    def running(self) -> bool:
        """Between :meth:`open` and :meth:`close`."""
        return self._tg is not None

    async def open(self) -> None:
        """Enter the task group (from the task that owns the part)."""
        if self._tg is not None:
            raise RuntimeError("background tasks already open")
        tg = asyncio.TaskGroup()
        await tg.__aenter__()
        self._tg = tg

    def start(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        """Run ``coro`` until :meth:`close` (or until it ends by itself)."""
        if self._tg is None:
            coro.close()
            raise RuntimeError(f"background task {name!r} started before open()")
        task = self._tg.create_task(coro, name=name)
        self._tasks.append(task)
        return task

    async def close(self) -> None:
        """Cancel every task and wait for them to end; raises (as an ExceptionGroup) what a
        task raised other than its cancellation. Closing twice, or before open, does nothing."""
        tg, self._tg = self._tg, None
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        if tg is not None:
            await tg.__aexit__(None, None, None)
