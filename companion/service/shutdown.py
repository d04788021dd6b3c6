"""A service stop that always ends: every wait on the way out is bounded and names what did not stop.

* :func:`bounded` awaits one step of the stop (the hand-over, a part's close) for at most its
  limit, in a task of its own, so a step stuck on a task that swallows its cancellation is
  logged with its stack and left behind instead of holding the stop;
* :class:`BoundedExit` does that for an async context manager's exit (the parts the service
  opens under its exit stack);
* :func:`dump_state` logs every asyncio task still alive with its stack, each thread's stack
  and each worker process's state: what a stop that overran its bound was waiting for;
* :class:`ShutdownWatch`, a thread, covers an event loop that is blocked outright: past the
  whole stop's bound it dumps that state, kills the worker processes and, for the ``companion
  run`` process, exits it (systemd then restarts the unit when it was not being stopped).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import threading
import time
import traceback
from collections.abc import Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from types import TracebackType
from typing import Generic, TypeVar

from companion.background import stop_tasks, task_stack
from planner.process import WorkerProcess

log = logging.getLogger(__name__)

T = TypeVar("T")

#: A step that overran its bound gets this long to end once cancelled before it is left behind.
CANCEL_GRACE_S = 2.0
#: How long the watch thread waits for the event loop to log its own tasks before reading them itself.
LOOP_ANSWER_S = 1.0
#: ``companion run``'s exit code when its stop overran the whole bound (EX_SOFTWARE).
HUNG_STOP_EXIT_CODE = 70


@dataclass(frozen=True)
class Worker:
    """A worker process the service holds, by name (None when it has none now)."""

    name: str
    process: Callable[[], WorkerProcess | None]


def worker_states(workers: Sequence[Worker]) -> list[str]:
    """``"perception: pid 123 still running"`` for each worker."""
    out = []
    for w in workers:
        proc = w.process()
        out.append(f"{w.name}: none" if proc is None else f"{w.name}: pid {proc.pid} {proc.exit_reason()}")
    return out


def kill_workers(workers: Sequence[Worker]) -> None:
    """SIGKILL every worker process still alive (never raises)."""
    for w in workers:
        proc = w.process()
        if proc is not None and proc.is_alive():
            log.error("killing the %s process (pid %s)", w.name, proc.pid)
            with contextlib.suppress(OSError):
                proc.kill()


def _thread_stacks() -> str:
    names = {t.ident: t.name for t in threading.enumerate()}
    parts = []
    for ident, frame in sys._current_frames().items():
        parts.append(f"thread {names.get(ident, ident)}:\n" + "".join(traceback.format_stack(frame)).rstrip())
    return "\n".join(parts)


def dump_state(why: str, workers: Sequence[Worker], loop: asyncio.AbstractEventLoop | None = None,
               threads: bool = False) -> None:
    """Log (ERROR) every asyncio task of ``loop`` still alive with its stack, each worker
    process's state and, with ``threads``, every thread's stack: what a stop was waiting for.
    From another thread, pass the loop (its tasks are then read while it may run)."""
    try:
        current = asyncio.current_task() if loop is None else None
        tasks = [t for t in asyncio.all_tasks(loop) if t is not current and not t.done()]
    except RuntimeError:
        tasks = []
    lines = [f"{why}: {len(tasks)} asyncio tasks still alive"]
    for task in sorted(tasks, key=lambda t: t.get_name()):
        lines.append(f"task {task.get_name()!r}:\n{task_stack(task)}")
    lines.extend(f"worker {s}" for s in worker_states(workers))
    if threads:
        lines.append(_thread_stacks())
    log.error("\n".join(lines))


async def bounded(aw: Awaitable[T], timeout_s: float, what: str) -> tuple[bool, T | None]:
    """Await ``aw`` for at most ``timeout_s`` in a task of its own: ``(True, result)`` when it
    ended in time (its error is raised), else ``(False, None)`` after it was cancelled and,
    if it ignored that for :data:`CANCEL_GRACE_S`, left running (logged with its stack)."""
    task: asyncio.Task[T] = asyncio.ensure_future(aw)
    task.set_name(what)
    try:
        done, _ = await asyncio.wait({task}, timeout=timeout_s)
    except asyncio.CancelledError:
        task.cancel()
        raise
    if done:
        return True, task.result()
    log.error("%s did not end within %.0f s; cancelling it", what, timeout_s)
    if not await stop_tasks([task], CANCEL_GRACE_S, what) and not task.cancelled() and task.exception():
        log.error("%s failed while being cancelled: %r", what, task.exception())
    return False, None


class BoundedExit(AbstractAsyncContextManager[T], Generic[T]):
    """``inner`` entered as it is, its exit bounded by ``timeout_s`` (:func:`bounded`).
    ``on_overrun`` runs when the exit overran (e.g. to log the service's state)."""

    def __init__(self, inner: AbstractAsyncContextManager[T], timeout_s: float, what: str,
                 on_overrun: Callable[[str], None] | None = None) -> None:
        self.inner = inner
        self.timeout_s = timeout_s
        self.what = what
        self.on_overrun = on_overrun

    async def __aenter__(self) -> T:
        return await self.inner.__aenter__()

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> bool | None:
        ended, suppress = await bounded(self.inner.__aexit__(exc_type, exc, tb), self.timeout_s,
                                        f"closing {self.what}")
        if not ended and self.on_overrun is not None:
            self.on_overrun(f"closing {self.what} overran {self.timeout_s:.0f} s")
        return suppress


class ShutdownWatch:
    """A thread that ends a stop the event loop cannot: armed when the stop begins, disarmed
    when it has ended. Past ``timeout_s`` it logs the state (:func:`dump_state`, threads
    included), kills the ``workers`` and, with ``exit_code``, ends the process."""

    def __init__(self, timeout_s: float, workers: Sequence[Worker], *, exit_code: int | None = None) -> None:
        self.timeout_s = timeout_s
        self.workers = list(workers)
        self.exit_code = exit_code
        #: True once the watch fired.
        self.fired = False
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def arm(self) -> None:
        """Start watching (on the event loop's thread)."""
        if self._thread is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._thread = threading.Thread(target=self._watch, name="shutdown-watch", daemon=True)
        self._thread.start()

    def disarm(self) -> None:
        """The stop has ended: the watch does nothing more."""
        self._done.set()

    def _watch(self) -> None:
        if self._done.wait(self.timeout_s):
            return
        self.fired = True
        why = f"the service's stop did not end within {self.timeout_s:.0f} s"
        loop = self._loop
        logged = threading.Event()

        def dump_on_loop() -> None:
            dump_state(why, self.workers, threads=True)
            logged.set()

        with contextlib.suppress(RuntimeError):  # the loop has closed
            assert loop is not None
            loop.call_soon_threadsafe(dump_on_loop)
        if not logged.wait(LOOP_ANSWER_S):
            # The loop is blocked: read its tasks from here (they cannot move meanwhile).
            dump_state(why + " (the event loop is blocked)", self.workers, loop=loop, threads=True)
        kill_workers(self.workers)
        if self.exit_code is not None and not self._done.is_set():
            log.critical("ending the process (exit code %d): its stop hung", self.exit_code)
            logging.shutdown()
            time.sleep(0.1)
            os._exit(self.exit_code)

