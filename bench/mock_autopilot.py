"""Mock autopilot figures: command-ack latency, telemetry rates, real-time factor, MAVSDK transfer.

``python bench/mock_autopilot.py [--quick]``

Cases (all on loopback, the mock in this process's event loop, like the tests):

* ``command_ack``: a raw pymavlink client sends ``COMMAND_LONG`` (MAV_CMD_REQUEST_MESSAGE for
  HOME_POSITION, a harmless command) one at a time and times the COMMAND_ACK, ``time.monotonic()``
  from just before ``sendto`` to the parsed ack. Target (PX4-like): p99 < 500 ms.
* ``telemetry``: messages per second the client receives for the main streams, next to the
  configured rate.
* ``realtime``: simulated seconds (physics ticks x dt) per wall second; 1.0 = keeping up.
* ``mavsdk``: the real MAVSDK core: time to discover the autopilot, then upload and download
  a mission of N waypoints through MissionRaw.

Measured figures depend on machine load; the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.geo import GeoOrigin  # noqa: E402
from companion.mavsdk_client import MavsdkClient  # noqa: E402
from companion.missions import MissionPlan, Waypoint  # noqa: E402
from companion.sim.autopilot import MockAutopilot  # noqa: E402

ACK_TARGET_MS_P99 = 500.0
STREAMS = ("HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT",
           "SYS_STATUS", "EXTENDED_SYS_STATE")


def _percentile(values: list[float], q: float) -> float:
    s = sorted(values)
    if not s:
        return float("nan")
    k = min(len(s) - 1, max(0, round(q / 100.0 * (len(s) - 1))))
    return s[k]


def _udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def _drain(sock: socket.socket, counts: dict[str, int]) -> list[Any]:
    out = []
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return out
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        for msg in parser.parse_buffer(data) or []:
            counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1
            out.append(msg)


async def _raw_cases(n_commands: int, telemetry_s: float) -> dict[str, Any]:
    sock = _udp_socket()
    port = sock.getsockname()[1]
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    counts: dict[str, int] = {}
    async with MockAutopilot(local_port=0, remote_ports=[port]) as ap:
        addr = ("127.0.0.1", ap.local_port)
        await asyncio.sleep(0.5)
        _drain(sock, counts)
        # telemetry rates
        counts.clear()
        t0 = time.monotonic()
        stamp0 = ap.vehicle.stamp_s
        while time.monotonic() - t0 < telemetry_s:
            await asyncio.sleep(0.01)
            _drain(sock, counts)
        wall = time.monotonic() - t0
        sim = ap.vehicle.stamp_s - stamp0
        rates = {name: counts.get(name, 0) / wall for name in STREAMS}
        configured = {name: ap.stream_rate_hz(name) for name in STREAMS}
        # command acks
        lat_ms: list[float] = []
        lost = 0
        for i in range(n_commands):
            msg = mav.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                          mavlink.MAVLINK_MSG_ID_HOME_POSITION, i, 0, 0, 0, 0, 0)
            buf = msg.pack(mav)
            mav.seq = (mav.seq + 1) % 256
            t_send = time.monotonic()
            sock.sendto(buf, addr)
            got = None
            while got is None and time.monotonic() - t_send < 2.0:
                for m in _drain(sock, counts):
                    if m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
                        got = time.monotonic()
                if got is None:
                    await asyncio.sleep(0.0005)
            if got is None:
                lost += 1
            else:
                lat_ms.append((got - t_send) * 1000.0)
    sock.close()
    return {
        "command_ack": {
            "n": n_commands, "lost": lost,
            "latency_ms_p50": _percentile(lat_ms, 50), "latency_ms_p95": _percentile(lat_ms, 95),
            "latency_ms_p99": _percentile(lat_ms, 99), "latency_ms_max": max(lat_ms, default=float("nan")),
            "latency_ms_mean": statistics.fmean(lat_ms) if lat_ms else float("nan"),
        },
        "telemetry": {
            **{f"{k.lower()}_hz": v for k, v in rates.items()},
            **{f"{k.lower()}_configured_hz": v for k, v in configured.items()},
        },
        "realtime": {"sim_s_per_wall_s": sim / wall, "wall_s": wall},
    }


async def _mavsdk_case(n_waypoints: int) -> dict[str, Any]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    home = GeoOrigin()
    wps = tuple(Waypoint(xyz_map_m=(float(i % 10), float(i // 10), 2.0), speed_m_s=1.0)
                for i in range(n_waypoints))
    async with MockAutopilot(local_port=0, remote_ports=[port], home=home) as ap:
        t0 = time.monotonic()
        async with MavsdkClient(f"udpin://127.0.0.1:{port}") as client:
            t_conn = time.monotonic() - t0
            t1 = time.monotonic()
            imap = await client.upload_mission(MissionPlan(wps, home, "bench"))
            t_up = time.monotonic() - t1
            t2 = time.monotonic()
            plan = await client.download_mission()
            t_down = time.monotonic() - t2
        assert len(ap.mission_items()) == len(imap.items)
        assert len(plan.waypoints) == n_waypoints
    return {"connect_ms": t_conn * 1000.0, "waypoints": n_waypoints, "items": len(imap.items),
            "upload_ms": t_up * 1000.0, "download_ms": t_down * 1000.0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small version (well under a minute)")
    args = ap.parse_args()
    n_cmd, tel_s, n_wp = (100, 3.0, 20) if args.quick else (1000, 10.0, 200)

    raw = asyncio.run(_raw_cases(n_cmd, tel_s))
    sdk = asyncio.run(_mavsdk_case(n_wp))
    ack = raw["command_ack"]
    print(f"mock autopilot bench ({'quick' if args.quick else 'full'}), "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    print(f"\ncommand ack latency over {ack['n']} commands ({ack['lost']} lost)")
    for k in ("p50", "p95", "p99", "max"):
        print(f"  {k:<5}{ack[f'latency_ms_{k}']:>9.2f} ms")
    ok = ack["latency_ms_p99"] < ACK_TARGET_MS_P99 and ack["lost"] == 0
    print(f"  target p99 < {ACK_TARGET_MS_P99:.0f} ms, none lost: {'met' if ok else 'NOT met'}")
    print(f"\ntelemetry over {raw['realtime']['wall_s']:.1f} s      received   configured")
    for name in STREAMS:
        k = name.lower()
        print(f"  {name:<24}{raw['telemetry'][f'{k}_hz']:>9.1f} Hz{raw['telemetry'][f'{k}_configured_hz']:>9.1f} Hz")
    print(f"\nreal-time factor (sim s / wall s): {raw['realtime']['sim_s_per_wall_s']:.3f}")
    print(f"\nMAVSDK: connect {sdk['connect_ms']:.0f} ms; mission of {sdk['waypoints']} waypoints "
          f"({sdk['items']} items): upload {sdk['upload_ms']:.0f} ms, download {sdk['download_ms']:.0f} ms")
    out = {"quick": bool(args.quick), "loadavg_1min": os.getloadavg()[0],
           "target_ack_ms_p99": ACK_TARGET_MS_P99, "target_met": bool(ok), **raw, "mavsdk": sdk}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
