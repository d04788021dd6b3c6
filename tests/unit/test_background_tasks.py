"""BackgroundTasks: the loops a part runs while it is open, and what happens when one fails."""

from __future__ import annotations

import asyncio
import builtins

import pytest

from companion.background import BackgroundTasks


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
