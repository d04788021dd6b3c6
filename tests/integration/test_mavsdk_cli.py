"""``companion sim-autopilot`` in a subprocess and ``companion mission ...`` through MAVSDK."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from companion.cli import main

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[2]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def sim_autopilot():  # type: ignore[no-untyped-def]
    local, api = _free_udp_port(), _free_udp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "sim-autopilot", "--local-port", str(local),
         "--offboard-port", str(api), "--gcs-port", "0", "--param", "COM_DISARM_PRFLT=-1"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30.0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind(("127.0.0.1", api))
            probe.settimeout(0.5)
            while True:  # wait for its first packet (it is up)
                try:
                    probe.recv(2048)
                    break
                except TimeoutError:
                    assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
                    assert time.monotonic() < deadline, "sim-autopilot did not start"
        yield f"udpin://127.0.0.1:{api}"
    finally:
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert "stopping mock autopilot" in err


def test_mission_upload_download_clear_via_cli(sim_autopilot, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    url = sim_autopilot
    plan = REPO / "tests" / "data" / "missions" / "qgc_simple.plan"
    assert main(["mission", "upload", str(plan), "--url", url]) == 0
    assert "uploaded" in capsys.readouterr().out
    out = tmp_path / "down.plan"
    assert main(["mission", "download", str(out), "--url", url]) == 0
    doc = json.loads(out.read_text(encoding="utf-8"))
    original = json.loads(plan.read_text(encoding="utf-8"))
    assert [i["command"] for i in doc["mission"]["items"]] == \
        [i["command"] for i in original["mission"]["items"]]
    assert main(["mission", "download", str(tmp_path / "down.yaml"), "--url", url]) == 0
    assert main(["mission", "check", str(tmp_path / "down.yaml")]) == 0
    assert main(["mission", "clear", "--url", url]) == 0
    assert main(["mission", "download", str(tmp_path / "empty.yaml"), "--url", url]) == 0
    assert "0 steps" in capsys.readouterr().out


def test_mission_cli_errors(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.yaml"
    bad.write_text("waypoints:\n  - {x_m: 1, y_m: 2, z_m: 1}\n  - {x_m: 1}\n", encoding="utf-8")
    assert main(["mission", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml: waypoints[1]: x_m and y_m go together" in err
    # No autopilot listening: a link failure (exit 1) naming the URL.
    url = f"udpin://127.0.0.1:{_free_udp_port()}"
    ok = REPO / "config" / "missions" / "square.yaml"
    assert main(["mission", "upload", str(ok), "--url", url, "--timeout", "0.5"]) == 1
    assert f"no autopilot heard on {url}" in capsys.readouterr().err
