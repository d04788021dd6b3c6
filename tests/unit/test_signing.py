"""MAVLink 2 signing end to end: key files, ``companion keygen``, the link and the mock
autopilot with the same key; unsigned packets are never believed."""

from __future__ import annotations

import asyncio
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from pymavlink.dialects.v20 import common as mavlink

from companion.config import config_from_dict
from companion.config_checks import check_runtime
from companion.errors import ConfigError
from companion.mavlink.link import MavlinkLink, SigningConfig
from companion.mavlink.signing import key_file_problem, read_key_file, write_key_file
from companion.sim.autopilot import MockAutopilot

REPO = Path(__file__).resolve().parents[2]


def test_keygen_writes_a_private_key_the_link_reads(tmp_path: Path) -> None:
    path = tmp_path / "mavlink.key"
    res = subprocess.run([sys.executable, "-m", "companion", "keygen", str(path)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    key = read_key_file(path)
    assert len(key) == 32 and path.read_text().strip() == key.hex()
    again = subprocess.run([sys.executable, "-m", "companion", "keygen", str(path)], cwd=REPO,
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "exists" in again.stderr
    assert read_key_file(path) == key  # not replaced


def test_key_files_readable_by_others_or_short_are_config_errors(tmp_path: Path) -> None:
    good = tmp_path / "good.key"
    write_key_file(good)
    assert key_file_problem(good) is None
    good.chmod(0o644)
    assert "chmod 600" in (key_file_problem(good) or "")
    short = tmp_path / "short.key"
    short.write_bytes(b"0123456789")
    short.chmod(0o600)
    assert "32 raw bytes" in (key_file_problem(short) or "")
    service = {"output_dir": str(tmp_path / "out"), "map_dir": str(tmp_path / "map")}
    cfg = config_from_dict({"link": {"signing_key_path": str(good)}, "service": service})
    with pytest.raises(ConfigError, match="link.signing_key_path"):
        check_runtime(cfg, "cfg.yaml")
    cfg_path = tmp_path / "cfg.yaml"
    cfg_path.write_text(yaml.safe_dump({"link": {"signing_key_path": str(short)}, "service": service}))
    res = subprocess.run([sys.executable, "-m", "companion", "config", "check", str(cfg_path)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "link.signing_key_path" in res.stderr and "short.key" in res.stderr


def _heartbeat(custom_mode: int) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return bytes(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, custom_mode,
                                      mavlink.MAV_STATE_ACTIVE).pack(mav))


@pytest.mark.asyncio
async def test_signed_link_and_signed_mock_talk_and_an_unsigned_spoof_is_never_believed(tmp_path: Path) -> None:
    key_path = tmp_path / "k"
    key = write_key_file(key_path)
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=20.0, signing=SigningConfig(key),
                           peer_system=1, peer_component=1, peer_timeout_s=0.5) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        ap = MockAutopilot(local_port=0, remote_ports=(port,), stream_rates_hz={"HEARTBEAT": 10.0})
        ap.enable_signing(key)
        spoofer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        spoofer.bind(("127.0.0.1", 0))
        try:
            async with ap:
                hb = await link.wait_message("HEARTBEAT", 3.0, lambda m: m.get_srcComponent() == 1)
                assert hb.get_signed()
                await ap.wait_until(lambda: (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER) in ap.peer_heartbeats, 3.0)
                # The autopilot goes silent past the peer timeout; an unsigned HEARTBEAT with its
                # ids claiming POSCTL (custom main mode 3) still picks nobody and is not dispatched.
                ap.faults.drop_link = True
                await asyncio.sleep(0.7)
                modes: list[int] = []
                remove = link.add_listener(lambda m: modes.append(m.custom_mode), ["HEARTBEAT"])
                for _ in range(20):
                    spoofer.sendto(_heartbeat(3 << 16), ("127.0.0.1", port))
                    await asyncio.sleep(0.01)
                await asyncio.sleep(0.1)
                remove()
                assert modes == []
                assert link.stats.peer == f"127.0.0.1:{ap.local_port}"
                assert link.stats.strangers_dropped >= 20
                # An unsigned packet to the mock is refused; the link's signed ones still count.
                ap.faults.drop_link = False
                spoofer.sendto(_heartbeat(0), ("127.0.0.1", ap.local_port))
                await asyncio.sleep(0.2)
                assert ap._link.unsigned_rejected >= 1  # noqa: SLF001 - the mock's own counter
                assert await link.wait_message("HEARTBEAT", 3.0, lambda m: m.get_srcComponent() == 1)
        finally:
            spoofer.close()
