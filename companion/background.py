"""The loops a long-lived part runs while it is open (a setpoint stream, a heartbeat, a feed).

A part opens its :class:`BackgroundTasks` in ``__aenter__``, starts its loops with
:meth:`BackgroundTasks.start`, and closes it in ``__aexit__``; a part that does nothing else
on entry and exit subclasses :class:`BackgroundPart` and only starts its loops. They run in an
:class:`asyncio.TaskGroup`: a loop that fails cancels the task that opened the part, so a part
whose loop died is never left looking alive. The group is left with ``(None, None, None)``, so
an exception from the owner's own ``async with`` body is not wrapped into an ExceptionGroup.

A part with a single loop ends it with :func:`end_task`; :func:`stop_tasks` ends any tasks
within a bound, cancelling again those that swallowed a cancellation and naming (with their
stacks) those that still run.
"""

from __future__ import annotations

import abc
import asyncio
import io
import logging
from collections.abc import Coroutine, Iterable
from types import TracebackType
from typing import Any, Self

log = logging.getLogger(__name__)


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
        task raised other than its cancellation. Closing twice, or before open, does nothing.

        The tasks are ended with :func:`stop_tasks` first, so one that swallows a cancellation
        is cancelled again and, if it still runs after :data:`TASK_STOP_TIMEOUT_S`, logged
        with its stack before the group waits for it."""
        tg, self._tg = self._tg, None
        tasks, self._tasks = self._tasks, []
        try:
            await stop_tasks(tasks, TASK_STOP_TIMEOUT_S, "closing background tasks")
        finally:
            # Also when a task's failure cancelled this (the group's owner): the group's exit
            # takes that cancellation back and raises the failure instead.
            if tg is not None:
                await tg.__aexit__(None, None, None)


class BackgroundPart(abc.ABC):
    """An async context manager that runs the loops :meth:`_start` starts while it is open."""

    def __init__(self) -> None:
        self._background = BackgroundTasks()

    @abc.abstractmethod
    def _start(self) -> None:
        """Start the part's loops with ``self._background.start``."""

    async def __aenter__(self) -> Self:
        await self._background.open()
        self._start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self._background.close()


#: How long a cancelled task may take to end before it is left behind (and logged).
TASK_STOP_TIMEOUT_S = 5.0
#: A task that has not ended is cancelled again this often: one that swallowed a cancellation
#: (a ``suppress(CancelledError)`` around an await) usually ends on the next.
RECANCEL_PERIOD_S = 1.0


def task_stack(task: asyncio.Task[Any]) -> str:
    """Where ``task`` is suspended now (its coroutine's stack), for a log line."""
    buf = io.StringIO()
    task.print_stack(file=buf)
    return buf.getvalue().rstrip()


async def stop_tasks(tasks: Iterable[asyncio.Task[Any]], timeout_s: float, what: str) -> list[asyncio.Task[Any]]:
    """Cancel ``tasks`` and wait up to ``timeout_s`` for them to end, cancelling again every
    :data:`RECANCEL_PERIOD_S`. Returns the ones still running, each logged with its stack
    (``what`` names the step); a task's own error is left for its owner to read.

    The caller's own cancellation is never swallowed (unlike ``suppress(CancelledError)``
    around ``await task``)."""
    pending = {t for t in tasks if not t.done()}
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while pending:
        for task in pending:
            task.cancel()
        remaining = deadline - loop.time()
        if remaining <= 0.0:
            break
        try:
            _, pending = await asyncio.wait(pending, timeout=min(RECANCEL_PERIOD_S, remaining))
        except asyncio.CancelledError:
            for task in pending:  # the caller is going: these get one more cancellation on the way
                task.cancel()
            raise
    stuck = sorted(pending, key=lambda t: t.get_name())
    for task in stuck:
        log.error("%s: task %r did not end within %.1f s of being cancelled; it is left running at:\n%s",
                  what, task.get_name(), timeout_s, task_stack(task))
    return stuck


async def end_task(task: asyncio.Task[Any] | None, what: str, timeout_s: float = TASK_STOP_TIMEOUT_S,
                   *, log_error: bool = False) -> None:
    """Cancel a part's loop and wait (bounded, :func:`stop_tasks`) for it to end; raises what
    the loop raised other than its cancellation, or with ``log_error`` logs it (for a task
    whose failure its owner has already acted on: it has ended either way)."""
    if task is None:
        return
    await stop_tasks([task], timeout_s, what)
    if task.done() and not task.cancelled() and task.exception() is not None:
        if not log_error:
            raise task.exception()  # type: ignore[misc]
        log.error("%s: it had failed: %r", what, task.exception())
