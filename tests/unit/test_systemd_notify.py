"""sd_notify over a real unix datagram socket standing in for systemd, and the watchdog."""

from __future__ import annotations

import asyncio
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.systemd_notify import SystemdNotifier, Watchdog, watchdog_timeout_s

WAIT_S = 10.0


class FakeSystemd:
    """The receiving end of ``$NOTIFY_SOCKET``: a bound unix datagram socket."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.setblocking(False)

    def recv(self, timeout_s: float = WAIT_S) -> dict[str, str]:
        self.sock.settimeout(timeout_s)
        data = self.sock.recv(4096).decode()
        return dict(line.split("=", 1) for line in data.split("\n"))

    def drain(self) -> list[dict[str, str]]:
        out = []
        self.sock.setblocking(False)
        while True:
            try:
                data = self.sock.recv(4096).decode()
            except BlockingIOError:
                return out
            out.append(dict(line.split("=", 1) for line in data.split("\n")))

    async def recv_async(self) -> dict[str, str]:
        return await asyncio.wait_for(asyncio.to_thread(self.recv), WAIT_S + 1)


@pytest.fixture
def systemd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[FakeSystemd]:
    path = str(tmp_path / "notify.sock")
    fake = FakeSystemd(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    yield fake
    fake.sock.close()


def test_ready_status_stopping_reach_the_socket(systemd: FakeSystemd) -> None:
    n = SystemdNotifier.from_env()
    assert n.enabled
    assert n.ready("mapping, 3 objects")
    assert systemd.recv() == {"READY": "1", "STATUS": "mapping, 3 objects"}
    assert n.status("line one\nline two")  # a newline would end the assignment
    assert systemd.recv() == {"STATUS": "line one line two"}
    assert n.watchdog()
    assert systemd.recv() == {"WATCHDOG": "1"}
    assert n.extend_timeout(2.5)
    assert systemd.recv() == {"EXTEND_TIMEOUT_USEC": "2500000"}
    assert n.stopping()
    assert systemd.recv() == {"STOPPING": "1"}
    n.close()


def test_abstract_namespace_socket(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"companion-test-{uuid.uuid4().hex}"
    fake = FakeSystemd("\0" + name)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        n = SystemdNotifier.from_env()
        assert n.ready()
        assert fake.recv() == {"READY": "1"}
        n.close()
    finally:
        fake.sock.close()


def test_without_systemd_everything_is_a_quiet_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = SystemdNotifier.from_env()
    assert not n.enabled
    assert not n.ready() and not n.watchdog()


def test_a_dead_socket_is_logged_once_and_never_raises(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    n = SystemdNotifier(str(tmp_path / "gone.sock"))
    assert n.enabled
    assert not n.ready()
    assert not n.watchdog()
    assert sum("sd_notify" in r.getMessage() for r in caplog.records) == 1
    assert not SystemdNotifier("relative/path").enabled


def test_watchdog_timeout_from_environment() -> None:
    pid = str(os.getpid())
    assert watchdog_timeout_s({"WATCHDOG_USEC": "10000000"}) == 10.0
    assert watchdog_timeout_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": pid}) == 4.0
    assert watchdog_timeout_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_timeout_s({"WATCHDOG_USEC": "bogus"}) is None
    assert watchdog_timeout_s({}) is None


def test_watchdog_check_pings_only_while_every_loop_is_alive(systemd: FakeSystemd) -> None:
    now = [100.0]
    wd = Watchdog(SystemdNotifier.from_env(), timeout_s=2.0, clock=lambda: now[0])
    assert wd.interval_s == 1.0
    wd.register("perception", max_silence_s=3.0)
    wd.register("planner", max_silence_s=10.0)
    assert wd.check()
    assert systemd.recv() == {"WATCHDOG": "1"}

    now[0] += 5.0
    wd.alive("planner")
    assert wd.stale() == ["perception"]
    assert not wd.check()
    status = systemd.recv()
    assert "WATCHDOG" not in status and "perception silent 5.0 s" in status["STATUS"]
    assert not wd.check()
    assert systemd.drain() == []  # still hung: no ping, and the status is not repeated

    wd.alive("perception")
    assert wd.check()
    assert systemd.recv() == {"WATCHDOG": "1"}
    wd.unregister("perception")
    now[0] += 20.0
    assert wd.stale() == ["planner"]
    assert wd.pings == 2


@pytest.mark.asyncio
async def test_watchdog_task_stops_pinging_when_a_loop_hangs(
    systemd: FakeSystemd, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "200000")  # 0.2 s: a ping every 0.1 s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    beating = asyncio.Event()
    beating.set()

    async with Watchdog(SystemdNotifier.from_env()) as wd:
        assert wd.interval_s == pytest.approx(0.1)
        wd.register("loop", max_silence_s=0.3)

        async def heart() -> None:
            while True:
                await beating.wait()
                wd.alive("loop")
                await asyncio.sleep(0.02)

        task = asyncio.create_task(heart())
        for _ in range(3):
            assert await systemd.recv_async() == {"WATCHDOG": "1"}

        beating.clear()  # the loop hangs
        while "STATUS" not in (msg := await systemd.recv_async()):
            assert msg == {"WATCHDOG": "1"}
        assert msg["STATUS"].startswith("unhealthy: loop silent")
        await asyncio.sleep(0.5)  # several ticks with the loop still hung
        assert systemd.drain() == []

        beating.set()  # it recovers: pings resume
        assert await systemd.recv_async() == {"WATCHDOG": "1"}
        task.cancel()
    assert wd._task is None
