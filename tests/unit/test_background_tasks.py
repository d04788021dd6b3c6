"""BackgroundTasks: the loops a part runs while it is open, and what happens when one fails."""

from __future__ import annotations

import asyncio
import builtins

import pytest

from companion.background import BackgroundTasks, end_task


async def _forever(ticks: list[int]) -> None:
    while True:
        ticks.append(1)
        await asyncio.sleep(0.001)


def test_tasks_run_while_open_and_are_cancelled_by_close() -> None:
    async def main() -> tuple[list[asyncio.Task[object]], int, int]:
        ticks: list[int] = []
        bg = BackgroundTasks()
        await bg.open()
        assert bg.running
        tasks = [bg.start(_forever(ticks), name="a"), bg.start(_forever(ticks), name="b")]
        await asyncio.sleep(0.05)
        await bg.close()
        n = len(ticks)
        await asyncio.sleep(0.02)
        assert not bg.running
        await bg.close()  # twice is fine
        return tasks, n, len(ticks)  # type: ignore[return-value]

    tasks, n_at_close, n_later = asyncio.run(main())
    assert n_at_close > 0 and n_later == n_at_close
    assert all(t.cancelled() for t in tasks)
    assert [t.get_name() for t in tasks] == ["a", "b"]


def test_a_failing_task_cancels_its_owner_and_close_raises_it() -> None:
    async def broken() -> None:
        await asyncio.sleep(0.01)
        raise ValueError("loop died")

    async def owner(bg: BackgroundTasks) -> None:
        await bg.open()
        bg.start(broken(), name="broken")
        await asyncio.sleep(10.0)  # the part's user, busy: cancelled by the failure

    async def main() -> BaseException | None:
        bg = BackgroundTasks()
        task = asyncio.create_task(owner(bg))
        with pytest.raises(asyncio.CancelledError):
            await asyncio.wait_for(task, 2.0)
        try:
            await bg.close()
        except BaseException as exc:
            return exc
        return None

    err = asyncio.run(main())
    assert isinstance(err, builtins.ExceptionGroup)  # a TaskGroup's (Python 3.11)
    assert any(isinstance(e, ValueError) and "loop died" in str(e) for e in err.exceptions)


def test_the_owners_own_error_is_not_wrapped() -> None:
    class Part:
        def __init__(self) -> None:
            self.bg = BackgroundTasks()

        async def __aenter__(self) -> Part:
            await self.bg.open()
            self.bg.start(asyncio.sleep(10.0), name="sleep")
            return self

        async def __aexit__(self, *exc: object) -> None:
            await self.bg.close()

    async def main() -> None:
        async with Part():
            raise KeyError("the caller's")

    with pytest.raises(KeyError, match="the caller's"):
        asyncio.run(main())


def test_start_before_open_is_refused_and_open_twice_too() -> None:
    async def main() -> None:
        bg = BackgroundTasks()
        with pytest.raises(RuntimeError, match="before open"):
            bg.start(asyncio.sleep(0), name="early")
        await bg.open()
        with pytest.raises(RuntimeError, match="already open"):
            await bg.open()
        await bg.close()

    asyncio.run(main())


def test_close_cancels_again_a_loop_that_swallowed_its_cancellation() -> None:
    async def stubborn(ended: list[bool]) -> None:
        try:
            await asyncio.sleep(10.0)
        except asyncio.CancelledError:
            pass  # swallowed once, as a careless ``suppress`` would
        await asyncio.sleep(10.0)  # the second cancellation ends it
        ended.append(False)

    async def main() -> list[bool]:
        ended: list[bool] = []
        bg = BackgroundTasks()
        await bg.open()
        task = bg.start(stubborn(ended), name="stubborn")
        await asyncio.sleep(0.01)
        await asyncio.wait_for(bg.close(), 3.0)
        assert task.cancelled()
        return ended

    assert asyncio.run(main()) == []


def test_a_loop_failing_while_being_closed_is_raised_by_close() -> None:
    async def fails_on_cancel() -> None:
        try:
            await asyncio.sleep(10.0)
        except asyncio.CancelledError:
            raise OSError("socket gone while closing") from None

    async def main() -> BaseException | None:
        bg = BackgroundTasks()
        await bg.open()
        bg.start(fails_on_cancel(), name="flaky")
        await asyncio.sleep(0.01)
        try:
            async with asyncio.timeout(3.0):  # close from the owner's own task, as a part does
                await bg.close()
        except BaseException as exc:
            return exc
        return None

    err = asyncio.run(main())
    assert isinstance(err, builtins.ExceptionGroup)
    assert any(isinstance(e, OSError) for e in err.exceptions)


def test_end_task_raises_or_logs_the_loops_failure(caplog: pytest.LogCaptureFixture) -> None:
    async def failed() -> None:
        raise ValueError("leg failed")

    async def main(log_error: bool) -> None:
        task = asyncio.create_task(failed())
        await asyncio.sleep(0)
        await end_task(task, "the flight task", log_error=log_error)

    with pytest.raises(ValueError, match="leg failed"):
        asyncio.run(main(False))
    asyncio.run(main(True))
    assert "the flight task: it had failed" in caplog.text
