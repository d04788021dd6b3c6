"""The MQTT ground link against a real Mosquitto broker on loopback: latencies and sizes.

Run: ``python bench/ground_link.py`` or ``--quick`` (fewer samples, a few seconds). Needs
``/usr/sbin/mosquitto`` (Debian package ``mosquitto``). Sections:

* ``command``: a ground client publishes goal commands (QoS 1); time until the bridge hands
  the validated command to the service, and until the ground client has the reply;
* ``telemetry``: ``publish_telemetry`` on the vehicle until the ground client receives it;
* ``map``: building the map message (PNG + base64) for square grids, and its payload size;
* ``reconnect``: the broker is killed under a connected bridge and restarted 1 s later;
  time from the broker accepting connections again until the bridge's session is up
  (default backoff: 0.5 s doubling, with jitter).

Bridge and ground client run in one process and one event loop, so latencies include both
sides' Python work. The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import aiomqtt  # noqa: E402

from companion.config import MqttConfig  # noqa: E402
from companion.ground import CommandValidator, MqttBridge  # noqa: E402
from companion.ground.messages import encode, map_message  # noqa: E402
from semmap.costmap import Costmap, VerticalBand  # noqa: E402
from semmap.grid import GridSpec  # noqa: E402

VEHICLE = "bench1"
BASE = f"companion/{VEHICLE}"


class Broker:
    """A throwaway mosquitto on a free loopback port (persistence off)."""

    def __init__(self, workdir: Path) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            raise SystemExit("mosquitto not found: apt-get install mosquitto")
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = int(s.getsockname()[1])
        conf = workdir / "mosquitto.conf"
        # set_tcp_nodelay: without it mosquitto's Nagle + the peers' delayed ACKs add ~40 ms
        # to small messages (docs/mqtt.md recommends it for the real broker too).
        lines = [f"listener {self.port} 127.0.0.1", "allow_anonymous true", "persistence false",
                 "set_tcp_nodelay true"]
        if os.geteuid() == 0:  # stay root: mosquitto's own user cannot read the temp folder
            lines.append(f"user {pwd.getpwuid(0).pw_name}")
        conf.write_text("\n".join(lines) + "\n")
        self.cmd = [exe, "-c", str(conf)]
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> float:
        """Start and wait until it accepts connections; returns that moment (monotonic)."""
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return time.monotonic()
            except OSError:
                time.sleep(0.005)
        raise SystemExit("mosquitto did not start")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


def stats_ms(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1000.0
    return {"p50_ms": round(float(np.percentile(a, 50)), 2),
            "p95_ms": round(float(np.percentile(a, 95)), 2),
            "max_ms": round(float(a.max()), 2)}


def validator() -> CommandValidator:
    return CommandValidator(geofence_xy_m=(0.0, 0.0, 10.0, 10.0), max_altitude_m=3.0,
                            rate_limit_hz=1000.0, burst=1000)


async def command_and_telemetry(broker: Broker, n: int) -> dict[str, Any]:
    cfg = MqttConfig(port=broker.port, vehicle_id=VEHICLE)
    sent_s: dict[str, float] = {}
    replied_s: dict[str, float] = {}
    tel_rx_s: dict[float, float] = {}
    nodelay = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)
    async with aiomqtt.Client("127.0.0.1", broker.port, identifier="bench-ground",
                              socket_options=nodelay) as ground, \
            MqttBridge(cfg, validator()) as bridge:
        await ground.subscribe(f"{BASE}/reply", qos=1)
        await ground.subscribe(f"{BASE}/telemetry", qos=0)
        if not await bridge.wait_connected(10.0):
            raise SystemExit("bridge did not connect")

        async def pump() -> None:
            async for m in ground.messages:
                now = time.monotonic()
                body = json.loads(bytes(m.payload))  # type: ignore[arg-type]
                if m.topic.value.endswith("/reply"):
                    replied_s[body["request_id"]] = now
                else:
                    tel_rx_s[body["xyz_map_m"][0]] = now

        pump_task = asyncio.create_task(pump())
        delivered: list[float] = []
        for i in range(n):
            rid = f"g-{i}"
            payload = json.dumps({"schema_version": 1, "request_id": rid, "x_m": 1.0, "y_m": 2.0})
            sent_s[rid] = time.monotonic()
            await ground.publish(f"{BASE}/cmd/goal", payload, qos=1)
            async for cmd in bridge.commands():
                delivered.append(time.monotonic() - sent_s[cmd.request_id])
                break
            await asyncio.sleep(0.01)
        tel_tx_s: dict[float, float] = {}
        for i in range(n):
            x = float(i)
            tel_tx_s[x] = time.monotonic()
            bridge.publish_telemetry([x, 0.0, 0.6], [0, 0, 0], 0.0, True, True, "OFFBOARD")
            await asyncio.sleep(0.02)  # 50 Hz, ten times the service's rate
        await asyncio.sleep(0.5)
        pump_task.cancel()
    reply = [replied_s[r] - sent_s[r] for r in sent_s if r in replied_s]
    tel = [tel_rx_s[x] - tel_tx_s[x] for x in tel_tx_s if x in tel_rx_s]
    return {
        "command": {"n": n, "to_service": stats_ms(delivered), "to_reply": stats_ms(reply),
                    "replies_lost": n - len(reply)},
        # Telemetry is a latest-value topic: one replaced before it went out is not sent.
        "telemetry": {"n": n, **stats_ms(tel), "superseded": n - len(tel)},
    }


def map_sizes(quick: bool) -> dict[str, Any]:
    out: dict[str, Any] = {}
    rng = np.random.default_rng(0)
    for side in (100, 400) if quick else (100, 400, 1000):
        spec = GridSpec(0.05, (0.0, 0.0), (side, side))
        cost = np.zeros((side, side), np.uint8)
        for _ in range(side // 10):  # rectangles of obstacles and unknown space, like a room
            r, c = rng.integers(0, side - 10, 2)
            cost[r:r + rng.integers(3, 30), c:c + rng.integers(3, 30)] = rng.choice([254, 255, 120])
        cm = Costmap(spec, cost, VerticalBand(0.4, 0.8))
        times = []
        for _ in range(5 if quick else 20):
            t0 = time.perf_counter()
            payload = encode(map_message(VEHICLE, cm))
            times.append(time.perf_counter() - t0)
        out[f"{side}x{side}"] = {"build_p50_ms": stats_ms(times)["p50_ms"],
                                 "payload_kib": round(len(payload) / 1024, 1)}
    return out


async def reconnect(broker: Broker, rounds: int) -> dict[str, Any]:
    """Broker killed under a connected bridge, back after 1 s: time until the session is up.

    A fresh bridge per round, so each round starts from a settled backoff (as after a
    long session) rather than from the previous round's grown delay.
    """
    cfg = MqttConfig(port=broker.port, vehicle_id=VEHICLE)
    times = []
    for _ in range(rounds):
        async with MqttBridge(cfg, validator()) as bridge:
            if not await bridge.wait_connected(10.0):
                raise SystemExit("bridge did not connect")
            broker.stop()
            for _ in range(1000):  # until the bridge notices
                if not bridge.connected:
                    break
                await asyncio.sleep(0.01)
            await asyncio.sleep(1.0)  # down for a while: the backoff grows
            up_s = await asyncio.to_thread(broker.start)
            if not await bridge.wait_connected(30.0):
                raise SystemExit("bridge did not reconnect")
            times.append(time.monotonic() - up_s)
    return {"rounds": rounds, "down_s": 1.0, "reconnect_min_s": cfg.reconnect_min_s,
            "reconnect_max_s": cfg.reconnect_max_s, **stats_ms(times)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer samples (a few seconds)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)  # the reconnect case logs each refused attempt
    n = 50 if args.quick else 500
    with tempfile.TemporaryDirectory() as tmp:
        broker = Broker(Path(tmp))
        broker.start()
        try:
            figures = asyncio.run(command_and_telemetry(broker, n))
            figures["map"] = map_sizes(args.quick)
            figures["reconnect"] = asyncio.run(reconnect(broker, 2 if args.quick else 5))
        finally:
            broker.stop()
    c, t, r = figures["command"], figures["telemetry"], figures["reconnect"]
    print(f"{'case':<34}{'p50 ms':>10}{'p95 ms':>10}{'max ms':>10}")
    for name, s in (("command -> service", c["to_service"]), ("command -> reply at ground",
                                                              c["to_reply"]),
                    ("telemetry -> ground", t), ("broker back (1 s down) -> up", r)):
        print(f"{name:<34}{s['p50_ms']:>10.2f}{s['p95_ms']:>10.2f}{s['max_ms']:>10.2f}")
    print(f"replies lost: {c['replies_lost']} of {c['n']}; telemetry superseded before "
          f"sending: {t['superseded']} of {t['n']}")
    print(f"\n{'map grid':<34}{'build ms':>10}{'KiB':>10}")
    for size, m in figures["map"].items():
        print(f"{size:<34}{m['build_p50_ms']:>10.2f}{m['payload_kib']:>10.1f}")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
