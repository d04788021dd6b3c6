"""Offboard setpoint timing: period and jitter of the 50 Hz setpoint task, idle and under load.

``python bench/setpoints.py [--quick] [--rate-hz 50] [--seconds 20]``

What is measured: our real :class:`~companion.mavlink.offboard.SetpointStreamer` on a real
:class:`~companion.mavlink.link.MavlinkLink` (``udpout://`` to loopback) sends
SET_POSITION_TARGET_LOCAL_NED at ``--rate-hz``. The streamer, a receiver and the load each run
in their own process (so a scheduler setting of one case cannot leak into the next). Two
clocks are read, both ``time.monotonic()`` (CLOCK_MONOTONIC, shared by all processes):

* ``send``: in the streamer process, right after each setpoint is handed to the socket;
* ``recv``: in the receiver process, when ``recv()`` returns the datagram. The receiver
  stands in for the flight controller (which has a CPU of its own), so it asks for a short
  scheduler slice; its wake-up delay still adds to this clock, making it an upper bound.

Period = difference of consecutive timestamps; jitter = ``|period - 1/rate|``. Cases:

* ``idle``: no extra load; the streamer requests the service's scheduler slice
  (``link.scheduler_slice_ms``, see :mod:`companion.mavlink.sched`), as the service does;
* ``loaded``: the same with two busy-loop processes (one per core on a 2-core machine) at
  the same priority, started before and stopped after the case. Each starts its own session
  (``setsid``): independent programs, as other services are on the drone. With Linux's
  ``sched_autogroup`` (or systemd's per-service cgroups) they form their own scheduling
  group, and groups share the CPUs fairly whatever slice a task inside asks for;
* ``loaded_same_group``: the busy processes stay in our session, competing inside our
  group the way the service's own perception threads do - where the slice request acts;
* ``loaded_same_group_no_slice`` (reference): the same without the slice request;
* ``loaded_relative_sleep`` (reference): the task written the naive way,
  ``await asyncio.sleep(period)`` after each send, to show the drift that absolute
  ``time.monotonic()`` deadlines avoid (its mean rate falls below the target).
* ``service_heap``: no extra load, but the streamer's process holds a heap the size of the
  service's (``--heap-objects`` long-lived containers, 400k by default: the service process
  holds 160-180k after its imports, a pytest session several times that) and allocates
  containers that live a quarter of a second, so Python's cyclic collector runs its full
  (generation-2) collections (each case runs at least 10 s); the heap is frozen as the
  service does (:func:`companion.service.app.frozen_heap`);
* ``service_heap_unfrozen`` (reference): the same without the freeze: each full collection
  walks the whole heap on the event-loop thread and delays the setpoint task by its duration.
  For both, the duration of the full collections is measured too (``gc_full_ms_max``).

The machine's own load (other programs) is printed with the results: on a shared machine it
dominates the tail, so compare cases of one run, not runs of different moments.

Target: ``loaded`` p99 jitter <= 5 ms at 50 Hz. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import json
import multiprocessing as mp
import os
import socket
import sys
import time
from collections import deque
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.config import LinkConfig  # noqa: E402
from companion.mavlink.failsafe import PositionSetpoint  # noqa: E402
from companion.mavlink.link import MavlinkLink  # noqa: E402
from companion.mavlink.offboard import SetpointStreamer, encode_setpoint  # noqa: E402
from companion.mavlink.sched import request_short_slice  # noqa: E402
from companion.service.app import frozen_heap  # noqa: E402

SET_POSITION_TARGET_LOCAL_NED_ID = 84
TARGET_P99_JITTER_MS = 5.0
RECEIVER_SLICE_S = 0.0002


def _busy_loop(own_session: bool) -> None:
    """Burn one core until terminated (in a new session unless told otherwise)."""
    if own_session:
        os.setsid()
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def _receiver(port_out: Connection, stop_after_s: float, result_out: Connection) -> None:
    """Bind a UDP socket, report its port, timestamp every setpoint datagram until idle.

    The receiver stands in for the flight controller, which has a CPU of its own: it asks
    for a short scheduler slice so its own wake-up delay disturbs the measurement less.
    """
    request_short_slice(RECEIVER_SLICE_S)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port_out.send(sock.getsockname()[1])
    sock.settimeout(stop_after_s)
    stamps: list[float] = []
    try:
        while True:
            data = sock.recv(2048)
            now = time.monotonic()
            # MAVLink 2 header: magic 0xFD, msgid in bytes 7..9 (little endian).
            if len(data) >= 10 and data[0] == 0xFD:
                msgid = data[7] | (data[8] << 8) | (data[9] << 16)
                if msgid == SET_POSITION_TARGET_LOCAL_NED_ID:
                    stamps.append(now)
    except TimeoutError:
        pass
    finally:
        sock.close()
    result_out.send(stamps)


def _stats(stamps: list[float], rate_hz: float) -> dict[str, float]:
    t = np.asarray(stamps, dtype=np.float64)
    if len(t) < 3:
        return {"n": float(len(t))}
    period_ms = np.diff(t) * 1000.0
    nominal_ms = 1000.0 / rate_hz
    jitter_ms = np.abs(period_ms - nominal_ms)
    return {
        "n": float(len(t)),
        "rate_hz": float((len(t) - 1) / (t[-1] - t[0])),
        "period_ms_p50": float(np.percentile(period_ms, 50)),
        "period_ms_p99": float(np.percentile(period_ms, 99)),
        "period_ms_max": float(period_ms.max()),
        "jitter_ms_p50": float(np.percentile(jitter_ms, 50)),
        "jitter_ms_p99": float(np.percentile(jitter_ms, 99)),
        "jitter_ms_max": float(jitter_ms.max()),
    }


async def _relative_sleep_streamer(link: MavlinkLink, rate_hz: float, seconds: float,
                                   sp: PositionSetpoint, send_stamps: list[float]) -> None:
    """The naive reference: sleep one period after each send (drifts by the loop's overhead)."""
    period_s = 1.0 / rate_hz
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        link.send(encode_setpoint(link, sp, 1, 1))
        send_stamps.append(time.monotonic())
        await asyncio.sleep(period_s)


#: The ``service_heap`` cases' allocation churn: containers per 5 ms tick, and how many live.
CHURN_PER_TICK = 2000
CHURN_LIVE = 100_000


async def _churn() -> None:
    """Allocate like a busy service: short-lived containers (messages, records) that survive
    the young collections and die a quarter of a second later (400k a second: several times
    a flying service's rate, so that a 10 s case sees full collections at all)."""
    live: deque[list[int]] = deque(maxlen=CHURN_LIVE)
    while True:
        for i in range(CHURN_PER_TICK):
            live.append([i])
        await asyncio.sleep(0.005)


async def _stream(port: int, rate_hz: float, seconds: float, relative: bool, churn: bool) -> list[float]:
    sp = PositionSetpoint((1.0, 2.0, -1.5), yaw_rad=0.3, velocity_ned_m_s=(0.2, 0.0, 0.0))
    send_stamps: list[float] = []
    async with MavlinkLink(f"udpout://127.0.0.1:{port}", heartbeat_rate_hz=1.0) as link:
        churner = asyncio.create_task(_churn()) if churn else None
        if relative:
            await _relative_sleep_streamer(link, rate_hz, seconds, sp, send_stamps)
        else:
            streamer = SetpointStreamer(link, rate_hz, lambda: sp)
            streamer.on_sent = send_stamps.append
            async with streamer:
                await asyncio.sleep(seconds)
        if churner is not None:
            churner.cancel()
    return send_stamps


def _streamer_proc(port: int, rate_hz: float, seconds: float, relative: bool,
                   slice_s: float, heap_objects: int, freeze: bool, out: Connection) -> None:
    """The process under test: our setpoint task (optionally with the service's slice
    request, a service-sized heap and its freeze)."""
    if slice_s > 0:
        request_short_slice(slice_s)
    heap = [{"k": [i]} for i in range(heap_objects // 3)]  # 3 tracked containers each
    full_ms: list[float] = []
    t0 = [0.0]

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if info["generation"] == 2:
            if phase == "start":
                t0[0] = time.perf_counter()
            else:
                full_ms.append(1e3 * (time.perf_counter() - t0[0]))

    with frozen_heap() if freeze else contextlib.nullcontext():
        gc.callbacks.append(on_gc)
        try:
            stamps = asyncio.run(_stream(port, rate_hz, seconds, relative, churn=heap_objects > 0))
        finally:
            gc.callbacks.remove(on_gc)
    del heap
    out.send((stamps, full_ms))


def run_case(rate_hz: float, seconds: float, load_procs: int, relative: bool, slice_s: float,
             same_session: bool = False, heap_objects: int = 0, freeze: bool = False) -> dict[str, Any]:
    """One case: receiver, optional busy processes and the streamer, each its own process."""
    ctx = mp.get_context("fork")
    port_rx, port_tx = ctx.Pipe(duplex=False)
    res_rx, res_tx = ctx.Pipe(duplex=False)
    send_rx, send_tx = ctx.Pipe(duplex=False)
    receiver = ctx.Process(target=_receiver, args=(port_tx, 1.0, res_tx), daemon=True)
    receiver.start()
    busy = [ctx.Process(target=_busy_loop, args=(not same_session,), daemon=True)
            for _ in range(load_procs)]
    try:
        port = port_rx.recv()
        for p in busy:
            p.start()
        time.sleep(0.5 if busy else 0.0)  # let the load settle onto the cores
        streamer = ctx.Process(target=_streamer_proc,
                               args=(port, rate_hz, seconds, relative, slice_s, heap_objects, freeze, send_tx))
        streamer.start()
        send_stamps, full_ms = send_rx.recv() if send_rx.poll(seconds + 60.0) else ([], [])
        streamer.join(timeout=5.0)
    finally:
        for p in busy:
            p.terminate()
        for p in busy:
            p.join()
    recv_stamps = res_rx.recv() if res_rx.poll(5.0) else []
    receiver.join(timeout=5.0)
    out: dict[str, Any] = {"send": _stats(send_stamps, rate_hz), "recv": _stats(recv_stamps, rate_hz)}
    if heap_objects:
        out["heap_objects"] = heap_objects
        out["gc_full_collections"] = len(full_ms)
        out["gc_full_ms_max"] = round(max(full_ms), 2) if full_ms else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 s per case instead of 15 s")
    ap.add_argument("--rate-hz", type=float, default=50.0)
    ap.add_argument("--seconds", type=float, default=None, help="seconds per case")
    ap.add_argument("--load-procs", type=int, default=2, help="busy-loop processes for loaded cases")
    ap.add_argument("--slice-ms", type=float, default=LinkConfig().scheduler_slice_ms,
                    help="scheduler slice the streamer requests (the service default)")
    ap.add_argument("--heap-objects", type=int, default=400_000,
                    help="long-lived tracked objects in the service_heap cases")
    args = ap.parse_args(argv)
    seconds = args.seconds or (4.0 if args.quick else 15.0)
    slice_s = args.slice_ms / 1000.0
    n = args.load_procs
    h = args.heap_objects
    # name -> (busy processes, in our session?, relative-sleep reference?, slice requested,
    #          long-lived heap objects, heap frozen?)
    cases = {
        "idle": (0, False, False, slice_s, 0, False),
        "loaded": (n, False, False, slice_s, 0, False),
        "loaded_same_group": (n, True, False, slice_s, 0, False),
        "loaded_same_group_no_slice": (n, True, False, 0.0, 0, False),
        "loaded_relative_sleep": (n, False, True, slice_s, 0, False),
        "service_heap": (0, False, False, slice_s, h, True),
        "service_heap_unfrozen": (0, False, False, slice_s, h, False),
    }
    results: dict[str, Any] = {}
    for name, (procs, same_session, relative, case_slice_s, heap, freeze) in cases.items():
        results[name] = run_case(args.rate_hz, max(seconds, 10.0) if heap else seconds, procs, relative,
                                 case_slice_s, same_session, heap, freeze)

    cols = ["n", "rate_hz", "period_ms_p50", "period_ms_p99", "period_ms_max",
            "jitter_ms_p50", "jitter_ms_p99", "jitter_ms_max"]
    print(f"setpoint task at {args.rate_hz:.0f} Hz, {seconds:.0f} s per case, slice request "
          f"{args.slice_ms:.2f} ms, "
          f"{args.load_procs} busy processes in loaded cases, {mp.cpu_count()} CPUs, "
          f"load average before start {os.getloadavg()[0]:.1f}")
    print(f"{'case':<28}{'clock':<6}" + "".join(f"{c:>15}" for c in cols))
    for name, res in results.items():
        for clock in ("send", "recv"):
            row = res[clock]
            print(f"{name:<28}{clock:<6}" + "".join(
                f"{row.get(c, float('nan')):>15.2f}" for c in cols))
    for name in ("service_heap", "service_heap_unfrozen"):
        r = results[name]
        print(f"{name}: {r['heap_objects']:,} long-lived objects, {r['gc_full_collections']} full collections, "
              f"longest {r['gc_full_ms_max']:.1f} ms; longest setpoint period at the receiver "
              f"{r['recv'].get('period_ms_max', float('nan')):.1f} ms")
    loaded_p99 = results["loaded"]["recv"].get("jitter_ms_p99", float("nan"))
    ok = loaded_p99 <= TARGET_P99_JITTER_MS
    print(f"target: loaded p99 jitter at the receiver <= {TARGET_P99_JITTER_MS:.0f} ms: "
          f"{loaded_p99:.2f} ms -> {'met' if ok else 'NOT met'}")
    out = {
        "rate_hz": args.rate_hz,
        "seconds_per_case": seconds,
        "load_procs": args.load_procs,
        "slice_ms": args.slice_ms,
        "loadavg_1min_at_end": os.getloadavg()[0],
        "cpus": mp.cpu_count(),
        "target_jitter_ms_p99": TARGET_P99_JITTER_MS,
        "target_met": bool(ok),
        **results,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
