"""The systemd unit and sysusers snippet, checked by systemd's own tools.

``systemd-analyze verify`` exits 0 even for keys it ignores ("Unknown key ..., ignoring"),
so a unit counts as clean only with exit status 0 *and* no diagnostics; the negative tests
show that each kind of mistake is caught. verify also requires the ``ExecStart=`` binary to
exist, so the unit is checked as a copy whose ExecStart points at a stand-in executable.
"""

from __future__ import annotations

import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "companion.service"
SYSUSERS = REPO / "systemd" / "companion.sysusers.conf"
EXEC_PATH = "/opt/companion/.venv/bin/companion"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
SYSTEMD_SYSUSERS = shutil.which("systemd-sysusers") or "/usr/bin/systemd-sysusers"


def _require(tool: str) -> None:
    if not Path(tool).exists():
        pytest.fail(f"{tool} not found: install the Debian package 'systemd' (make test does)")


def unit_copy(tmp_path: Path, text: str | None = None) -> Path:
    """The unit (or ``text``) as tmp/companion.service, ExecStart on a stand-in binary."""
    stand_in = tmp_path / "bin" / "companion"
    stand_in.parent.mkdir(exist_ok=True)
    stand_in.write_text("#!/bin/sh\nexit 0\n")
    stand_in.chmod(stand_in.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    body = UNIT.read_text() if text is None else text
    assert EXEC_PATH in body
    out = tmp_path / "companion.service"
    out.write_text(body.replace(EXEC_PATH, str(stand_in)))
    return out


def verify(unit: Path) -> tuple[int, str]:
    """(exit status, diagnostics) of ``systemd-analyze verify``."""
    _require(SYSTEMD_ANALYZE)
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "verify", "--man=no", str(unit)],
        capture_output=True, text=True, timeout=120, cwd=unit.parent,
    )
    return proc.returncode, (proc.stdout + proc.stderr).strip()


def settings(text: str) -> dict[tuple[str, str], list[str]]:
    """(section, key) -> values in order (systemd keys may repeat)."""
    out: dict[tuple[str, str], list[str]] = {}
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if m := re.fullmatch(r"\[(\w+)\]", line):
            section = m.group(1)
            continue
        key, _, value = line.partition("=")
        out.setdefault((section, key.strip()), []).append(value.strip())
    return out


def test_unit_verifies_without_any_diagnostic(tmp_path: Path) -> None:
    rc, diag = verify(unit_copy(tmp_path))
    assert rc == 0 and diag == "", diag


@pytest.mark.parametrize(
    ("breakage", "old", "new", "expected"),
    [
        ("misspelt key", "WatchdogSec=10s", "WatchdogSecs=10s", "Unknown key"),
        ("bad value", "Type=notify", "Type=notified", "Failed to parse service type"),
        ("bad hardening value", "ProtectSystem=strict", "ProtectSystem=very", "protect system value"),
        ("missing binary", "ExecStart=" + EXEC_PATH, "ExecStart=/nonexistent/companion",
         "/nonexistent/companion"),
    ],
)
def test_a_broken_unit_fails_verification(
    tmp_path: Path, breakage: str, old: str, new: str, expected: str
) -> None:
    text = UNIT.read_text()
    assert old in text, breakage
    broken = text.replace(old, new)
    path = tmp_path / "companion.service"
    if breakage == "missing binary":
        path.write_text(broken)
    else:
        path = unit_copy(tmp_path, broken)
    rc, diag = verify(path)
    assert rc != 0 or diag != "", f"{breakage} went unnoticed"
    assert expected in diag, diag


def test_unit_runs_the_service_as_specified() -> None:
    s = settings(UNIT.read_text())
    assert s[("Service", "Type")] == ["notify"]
    assert s[("Service", "ExecStart")] == [
        f"{EXEC_PATH} run --config /etc/companion/companion.yaml"
    ]
    assert s[("Service", "Restart")] == ["on-failure"]
    assert s[("Service", "WatchdogSec")] == ["10s"]
    assert s[("Service", "User")] == ["companion"]
    assert set(s[("Service", "SupplementaryGroups")][0].split()) >= {"dialout", "video", "plugdev"}
    assert s[("Service", "StateDirectory")] == ["companion"]
    for key in ("NoNewPrivileges", "PrivateTmp", "ProtectHome", "ProtectKernelTunables"):
        assert s[("Service", key)] == ["yes"], key
    assert s[("Service", "ProtectSystem")] == ["strict"]
    families = set(s[("Service", "RestrictAddressFamilies")][0].split())
    assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= families
    assert not families & {"AF_PACKET", "AF_BLUETOOTH", "AF_CAN"}
    assert s[("Service", "DevicePolicy")] == ["closed"]
    assert "/dev/ttyTHS1 rw" in s[("Service", "DeviceAllow")]
    assert "char-video4linux rw" in s[("Service", "DeviceAllow")]
    assert s[("Install", "WantedBy")] == ["multi-user.target"]


def test_hardening_exposure_is_at_most_2_of_10() -> None:
    _require(SYSTEMD_ANALYZE)
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "security", "--offline=yes", "--man=no", "--threshold=20", str(UNIT)],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr


def test_sysusers_creates_the_user_with_device_groups(tmp_path: Path) -> None:
    _require(SYSTEMD_SYSUSERS)
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    proc = subprocess.run([SYSTEMD_SYSUSERS, f"--root={root}", str(SYSUSERS)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    passwd = {line.split(":")[0]: line.split(":") for line in (root / "etc/passwd").read_text().splitlines()}
    assert passwd["companion"][5] == "/var/lib/companion"
    assert passwd["companion"][6].endswith("nologin")
    groups = {line.split(":")[0]: line.split(":")[3].split(",")
              for line in (root / "etc/group").read_text().splitlines()}
    for g in ("dialout", "video", "plugdev"):
        assert "companion" in groups[g], g
