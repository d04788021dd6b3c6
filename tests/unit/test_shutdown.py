"""A stop that always ends: bounded task cancellation, bounded part closes, the watch thread."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from types import TracebackType
from typing import Any

import pytest

from companion.background import stop_tasks
from companion.service.shutdown import BoundedExit, ShutdownWatch, Worker, bounded


async def _swallows_cancellation(times: int, ended: list[str]) -> None:
    """Ignore the first ``times`` cancellations (``suppress(CancelledError)`` around an await)."""
    for _ in range(times):
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(3600)
    ended.append("ended")


async def _ignores_cancellation_until(release: asyncio.Event) -> None:
    while not release.is_set():
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(0.01)


def test_a_task_that_swallowed_a_cancellation_is_cancelled_again_and_ends() -> None:
    async def main() -> tuple[list[asyncio.Task[Any]], list[str]]:
        ended: list[str] = []
        task = asyncio.create_task(_swallows_cancellation(2, ended), name="swallower")
        await asyncio.sleep(0)
        return await stop_tasks([task], 5.0, "test"), ended

    stuck, ended = asyncio.run(main())
    assert stuck == [] and ended == ["ended"]


def test_a_task_that_ignores_every_cancellation_is_left_behind_and_logged_with_its_stack(
        caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> list[str]:
        release = asyncio.Event()
        task = asyncio.create_task(_ignores_cancellation_until(release), name="stubborn")
        await asyncio.sleep(0)
        stuck = await stop_tasks([task], 0.3, "stopping the test's tasks")
        names = [t.get_name() for t in stuck]
        release.set()
        await task
        return names

    with caplog.at_level(logging.ERROR):
        assert asyncio.run(main()) == ["stubborn"]
    msg = "\n".join(r.getMessage() for r in caplog.records)
    assert "stopping the test's tasks: task 'stubborn' did not end" in msg
    assert "_ignores_cancellation_until" in msg  # its stack names where it is stuck


def test_stop_tasks_never_swallows_the_callers_own_cancellation() -> None:
    async def main() -> bool:
        release = asyncio.Event()
        stubborn = asyncio.create_task(_ignores_cancellation_until(release), name="stubborn")
        stopper = asyncio.create_task(stop_tasks([stubborn], 60.0, "test"))
        await asyncio.sleep(0.05)
        stopper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stopper
        release.set()
        await stubborn
        return stopper.cancelled()

    assert asyncio.run(main())


class _HangsOnExit:
    """A part whose close waits for a loop that swallows its cancellation (the pattern
    ``task.cancel(); with suppress(CancelledError): await task`` with such a loop)."""

    def __init__(self, release: asyncio.Event) -> None:
        self.release = release
        self.task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> _HangsOnExit:
        self.task = asyncio.create_task(_ignores_cancellation_until(self.release), name="part-loop")
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        assert self.task is not None
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task


def test_a_part_whose_close_hangs_is_left_behind_within_its_bound() -> None:
    overruns: list[str] = []

    async def main() -> float:
        release = asyncio.Event()
        part = _HangsOnExit(release)
        t0 = time.monotonic()
        async with BoundedExit(part, 0.3, "the hanging part", on_overrun=overruns.append):
            t0 = time.monotonic()
        elapsed = time.monotonic() - t0
        release.set()
        await asyncio.sleep(0.05)
        return elapsed

    elapsed_s = asyncio.run(main())
    assert overruns == ["closing the hanging part overran 0 s"]
    assert elapsed_s < 30.0  # bounded (0.3 s + the cancel grace), not waiting for the release


def test_bounded_returns_the_result_and_raises_the_error_of_a_step_that_ends_in_time() -> None:
    async def ok() -> int:
        return 7

    async def fails() -> None:
        raise ValueError("boom")

    async def main() -> tuple[bool, int | None]:
        with pytest.raises(ValueError, match="boom"):
            await bounded(fails(), 1.0, "failing step")
        return await bounded(ok(), 1.0, "step")

    assert asyncio.run(main()) == (True, 7)


class _FakeProcess:
    """What the watch reads and kills of a worker process."""

    pid = 4242

    def __init__(self) -> None:
        self.killed = False

    def is_alive(self) -> bool:
        return not self.killed

    def exit_reason(self) -> str:
        return "killed by signal 9" if self.killed else "still running"

    def kill(self) -> None:
        self.killed = True


def test_the_watch_dumps_the_blocked_loops_tasks_and_the_workers_then_kills_the_workers(
        caplog: pytest.LogCaptureFixture) -> None:
    proc = _FakeProcess()

    async def idle_loop() -> None:
        await asyncio.sleep(3600)

    async def main() -> bool:
        task = asyncio.create_task(idle_loop(), name="idle-loop")
        await asyncio.sleep(0)
        watch = ShutdownWatch(0.2, [Worker("perception", lambda: proc)])  # type: ignore[arg-type,return-value]
        watch.arm()
        time.sleep(2.0)  # noqa: ASYNC251 - the event loop is blocked on purpose: only the thread can act
        watch.disarm()
        task.cancel()
        return watch.fired

    with caplog.at_level(logging.ERROR):
        assert asyncio.run(main())
    msg = "\n".join(r.getMessage() for r in caplog.records)
    assert "the event loop is blocked" in msg
    assert "task 'idle-loop'" in msg and "idle_loop" in msg
    assert "worker perception: pid 4242 still running" in msg
    assert "thread MainThread" in msg and "time.sleep(2.0)" in msg
    assert proc.killed


def test_a_watch_disarmed_in_time_does_nothing() -> None:
    proc = _FakeProcess()

    async def main() -> bool:
        watch = ShutdownWatch(0.5, [Worker("planner", lambda: proc)])  # type: ignore[arg-type,return-value]
        watch.arm()
        await asyncio.sleep(0.05)
        watch.disarm()
        await asyncio.sleep(0.8)
        return watch.fired

    assert asyncio.run(main()) is False
    assert not proc.killed
