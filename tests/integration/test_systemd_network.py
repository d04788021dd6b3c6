"""The unit's IP allow list and /proc subset (issue 33, item 7), checked by systemd itself."""

from __future__ import annotations

import subprocess

from test_systemd_unit import SYSTEMD_ANALYZE, UNIT, _require, settings


def _security_lines() -> dict[str, str]:
    _require(SYSTEMD_ANALYZE)
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "security", "--offline=yes", "--man=no", str(UNIT)],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    out = {}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[1].endswith("="):
            out[parts[1]] = line
    return out


def test_unit_denies_ip_peers_beyond_loopback_and_local_networks() -> None:
    s = settings(UNIT.read_text())
    assert s[("Service", "IPAddressDeny")] == ["any"]
    allowed = " ".join(s[("Service", "IPAddressAllow")]).split()
    assert "localhost" in allowed
    assert {"10.0.0.0/8", "172.16.0.0/12", "192.168.0.0/16"} <= set(allowed)
    assert "any" not in allowed and "0.0.0.0/0" not in allowed and "::/0" not in allowed
    # systemd reads it as an allow list (not "no IP restriction at all").
    line = _security_lines()["IPAddressDeny="]
    assert "allow list" in line, line


def test_unit_shows_only_processes_in_proc() -> None:
    assert settings(UNIT.read_text())[("Service", "ProcSubset")] == ["pid"]
    assert _security_lines()["ProcSubset="].lstrip().startswith("✓")
