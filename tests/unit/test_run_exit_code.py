"""``companion run``'s exit: a stop that overran (tasks left running after their cancellation)
ends the process with HUNG_STOP_EXIT_CODE, so systemd restarts a failed unit instead of
waiting on a process that never exits; a clean stop returns normally."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

import pytest

import companion.cli.run as run
import companion.service.app as app
import companion.sources as sources
from companion.config import CompanionConfig
from companion.service.shutdown import HUNG_STOP_EXIT_CODE


class _ExitCalledError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _fake_service(overruns: list[str], made: list[Any]) -> type:
    class FakeService:
        """Stands in for CompanionService: its run returns a report with ``overruns``."""

        def __init__(self, cfg: CompanionConfig, source: object, **kw: object) -> None:
            self.hung_stop_exit_code: int | None = None
            made.append(self)

        async def run(self, stop: asyncio.Event) -> SimpleNamespace:
            return SimpleNamespace(stop_overruns=list(overruns))

    return FakeService


def _cfg() -> CompanionConfig:
    cfg = CompanionConfig()
    return cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"source": "recorded"})})


@pytest.fixture()
def exits(monkeypatch: pytest.MonkeyPatch) -> None:
    def fake_exit(code: int) -> None:
        raise _ExitCalledError(code)

    monkeypatch.setattr(run.os, "_exit", fake_exit)
    monkeypatch.setattr(sources, "make_frame_source", lambda cfg: object())


def test_a_stop_that_overran_ends_the_process_with_the_hung_stop_exit_code(
        monkeypatch: pytest.MonkeyPatch, exits: None, caplog: pytest.LogCaptureFixture) -> None:
    made: list[Any] = []
    monkeypatch.setattr(app, "CompanionService", _fake_service(["stopping the service's tasks overran 5 s"], made))
    with pytest.raises(_ExitCalledError) as exc:
        asyncio.run(run._serve(_cfg(), fly_mission=False, out=None))
    assert exc.value.code == HUNG_STOP_EXIT_CODE == 70
    assert made[0].hung_stop_exit_code == HUNG_STOP_EXIT_CODE
    assert "the stop overran (stopping the service's tasks overran 5 s)" in caplog.text


def test_a_clean_stop_returns_without_forcing_an_exit(monkeypatch: pytest.MonkeyPatch, exits: None) -> None:
    made: list[Any] = []
    monkeypatch.setattr(app, "CompanionService", _fake_service([], made))
    asyncio.run(run._serve(_cfg(), fly_mission=False, out=None))
    assert len(made) == 1
