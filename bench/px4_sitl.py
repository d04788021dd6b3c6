"""Conformance against real PX4 SITL: the demo flight over seeded rooms, and the scenario probes.

``python bench/px4_sitl.py [--rooms N] [--quick] [--only NAME,...]``

Each room: a fresh PX4 SITL (SIH quadrotor, no lockstep, :mod:`companion.sim.px4_sitl`) and
``companion demo --autopilot px4-sitl``'s flight (:func:`companion.sim.demo_px4.fly_px4`):
the whole service flies the MAVSDK-uploaded crossing, judged against the room's ground truth;
PX4's own ``uorb top`` gives the rates at which it receives the companion's setpoints
(``offboard_control_mode``, one per SET_POSITION_TARGET_LOCAL_NED) and OBSTACLE_DISTANCE,
sampled every few seconds while in OFFBOARD. The scenario probes (:mod:`companion.sim.px4_probes`)
each get a fresh SITL:

* ``mission_start``: ``companion mission upload --start config/missions/square.yaml`` flies the
  square near home (never towards 0/0), lands there, and downloads back the same steps;
* ``engage``: in every room flight PX4 first reports OFFBOARD in the air at the take-off height;
* ``offboard_loss``: ``companion run`` killed in OFFBOARD in the air: PX4's failsafe
  (``COM_OF_LOSS_T`` 0.5 s, ``COM_OBL_RC_ACT`` 4 Land, as the README's PX4 table requires)
  leaves OFFBOARD, holds within 1 m and lands;
* ``landing_rearm``: after a landing in OFFBOARD (PX4 disarms, keeps the mode) the service
  takes off again;
* ``obstacle_distance``: PX4's uORB sees ``obstacle_distance`` at >= 8 Hz in flight.

Targets (>= 5 rooms): every waypoint reached, 0 collisions, setpoints >= 25 Hz and obstacle
distance >= 8 Hz at PX4, every scenario passing. ``e2e_latency_ms_p95`` (and ``_p50``) pools
every plan's frame-to-setpoint latency over all rooms (a flight makes 4-12 plans); each
room's row shows its own p95 and the detector's mean time per frame, which tracks the load. PX4 and the service load both cores: the
machine's load average is printed with the figures. ``--quick`` flies 1 room and checks the
scenarios that flight shows (engage, obstacle_distance); it takes 2-3 minutes, not 1 (PX4's
start, the perception process's warm-up and a flight across the room and back; 150 s measured
at load average 2-5). The full run took 630-643 s at load average 4-9. The last line is one JSON
object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._px4 import add_common_args, prepare, room_seeds, start_sitl, with_seed  # noqa: E402
from companion.sim.demo_px4 import Px4Flight, fly_px4  # noqa: E402
from companion.sim.px4_probes import (  # noqa: E402
    ProbeResult,
    probe_landing_rearm,
    probe_mission_start,
    probe_offboard_loss,
)
from companion.sim.px4_sitl import Px4SitlError  # noqa: E402

SETPOINT_TARGET_HZ = 25.0
OBSTACLE_TARGET_HZ = 8.0
SCENARIOS = ("mission_start", "engage", "offboard_loss", "landing_rearm", "obstacle_distance")
log = logging.getLogger("bench.px4_sitl")


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 1) if values else None


async def fly_rooms(cfg: Any, seeds: list[int], out: Path, timeout_s: float) -> list[Px4Flight]:
    flights = []
    for seed in seeds:
        c = with_seed(cfg, seed)
        try:
            sitl = await asyncio.to_thread(start_sitl, c, log)
        except Px4SitlError as exc:
            log.error("room %d not flown: %s", seed, exc)
            continue
        with sitl:
            t0 = time.monotonic()
            flight = await fly_px4(c, out / f"room-{seed}", sitl=sitl, timeout_s=timeout_s)
            log.info("room %d flown in %.0f s", seed, time.monotonic() - t0)
        flights.append(flight)
    return flights


async def run_probe(name: str, cfg: Any, out: Path) -> tuple[ProbeResult, Px4Flight | None]:
    try:
        sitl = await asyncio.to_thread(start_sitl, cfg, log)
    except Px4SitlError as exc:
        return ProbeResult(name, False, f"PX4 SITL not ready: {str(exc).splitlines()[0]}"), None
    with sitl:
        if name == "mission_start":
            return await probe_mission_start(sitl), None
        if name == "offboard_loss":
            work = out / "offboard-loss"
            work.mkdir(parents=True, exist_ok=True)
            return await probe_offboard_loss(sitl, cfg, work), None
        if name == "landing_rearm":
            return await probe_landing_rearm(sitl, cfg, out / "landing-rearm")
    raise ValueError(f"unknown probe {name!r}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap, rooms=5, quick_help="1 room; the scenarios that flight shows")
    ap.add_argument("--only", default=None, help=f"comma-separated scenarios to run ({', '.join(SCENARIOS)})")
    args = ap.parse_args()
    prepared = prepare(args, "px4_sitl", log)
    if prepared is None:
        return 2
    cfg, out = prepared
    n_rooms = 1 if args.quick else args.rooms
    wanted = SCENARIOS if args.only is None else tuple(x.strip() for x in args.only.split(","))
    if args.quick and args.only is None:
        wanted = ("engage", "obstacle_distance")
    unknown = set(wanted) - set(SCENARIOS)
    if unknown:
        print(f"--only: unknown scenarios {sorted(unknown)} (known: {', '.join(SCENARIOS)})", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    t0 = time.monotonic()
    seeds = room_seeds(cfg, args.seed, n_rooms) if n_rooms > 0 else []
    flights = asyncio.run(fly_rooms(cfg, seeds, out, args.timeout))
    probes: dict[str, ProbeResult] = {}
    for name in ("mission_start", "offboard_loss", "landing_rearm"):
        if name in wanted:
            t = time.monotonic()
            result, extra = asyncio.run(run_probe(name, cfg, out))
            probes[name] = result
            log.info("%s: %s in %.0f s", name, "pass" if result.passed else "FAIL", time.monotonic() - t)
            if extra is not None and name == "landing_rearm":
                ok_e, detail_e = extra.summary["engage"]["ok"], extra.summary["engage"]["detail"]
                probes[name].figures["engage_after_rearm"] = detail_e if ok_e else f"FAIL: {detail_e}"
    load1 = os.getloadavg()
    return report(flights, probes, wanted, out, time.monotonic() - t0, load0, load1)


def report(flights: list[Px4Flight], probes: dict[str, ProbeResult], wanted: tuple[str, ...], out: Path,
           elapsed_s: float, load0: tuple[float, float, float], load1: tuple[float, float, float]) -> int:
    print(f"PX4 SITL conformance: {len(flights)} rooms flown, {elapsed_s:.0f} s, outputs in {out}")
    print(f"machine: {os.cpu_count()} cores, load average (1 min) {load0[0]:.1f} at start, {load1[0]:.1f} at end "
          "(PX4 SITL and the whole service share them)")
    print(f"{'seed':>4} {'waypoints':>9} {'coll':>4} {'clear_m':>7} {'sp_Hz':>6} {'traj_Hz':>7} {'obst_Hz':>7} "
          f"{'e2e_p95_ms':>10} {'detect_ms':>9}  engage")
    setpoint_hz: list[float] = []
    obstacle_hz: list[float] = []
    e2e_ms: list[float] = []
    engage_ok = True
    for f in flights:
        s = f.summary
        sp = f.uorb_hz.get("offboard_control_mode", [])
        ob = f.uorb_hz.get("obstacle_distance", [])
        setpoint_hz += sp
        obstacle_hz += ob
        p95 = s["latency_ms"].get("frame_to_setpoint", {}).get("p95_ms")
        e2e_ms += s.get("frame_to_setpoint_ms", [])
        detect_ms = s["stage_timings_ms"].get("detect", {}).get("mean_ms")
        engage_ok &= bool(s["engage"]["ok"])
        print(f"{s['seed']:>4} {s['waypoints_reached']:>4}/{s['waypoints_total']:<4} {s['collisions']:>4} "
              f"{s['min_clearance_m'] if s['min_clearance_m'] is not None else '-':>7} {_median(sp) or '-':>6} "
              f"{_median(f.uorb_hz.get('trajectory_setpoint', [])) or '-':>7} {_median(ob) or '-':>7} "
              f"{p95 if p95 is not None else '-':>10} {detect_ms if detect_ms is not None else '-':>9}  "
              f"{'ok' if s['engage']['ok'] else 'FAIL'}: {s['engage']['detail']}")
        if s.get("mission_error"):
            print(f"     mission error: {s['mission_error']}")
    if e2e_ms:
        print(f"frame-to-setpoint latency over all {len(e2e_ms)} plans: p50 {np.percentile(e2e_ms, 50):.0f} ms, "
              f"p95 {np.percentile(e2e_ms, 95):.0f} ms (detect_ms: mean detector time per frame, the machine's load)")
    scenarios: dict[str, bool] = {}
    if "engage" in wanted and flights:
        scenarios["engage"] = engage_ok
    if "obstacle_distance" in wanted and flights:
        scenarios["obstacle_distance"] = bool(obstacle_hz) and float(np.median(obstacle_hz)) >= OBSTACLE_TARGET_HZ
    for name, r in probes.items():
        scenarios[name] = r.passed
    print("\nscenarios:")
    for name in SCENARIOS:
        if name in scenarios:
            detail = probes[name].detail if name in probes else ""
            print(f"  {name:<18} {'pass' if scenarios[name] else 'FAIL'}  {detail}")
            if name in probes and probes[name].figures:
                print(f"  {'':<18}       {probes[name].figures}")
    for f in flights:
        if not f.summary["engage"]["ok"] or f.summary.get("mission_error"):
            print(f"\nPX4 log, room {f.summary['seed']}:")
            for line in f.summary.get("px4_log_events", [])[-15:]:
                print(f"  {line}")
    for name, r in probes.items():
        print(f"\nPX4 log, {name} ({'pass' if r.passed else 'FAIL'}):")
        for line in r.px4_log[-12:]:
            print(f"  {line}")
    clear = [f.summary["min_clearance_m"] for f in flights if f.summary["min_clearance_m"] is not None]
    figures = {
        "rooms": len(flights),
        "waypoints_reached": sum(f.summary["waypoints_reached"] for f in flights),
        "waypoints_total": sum(f.summary["waypoints_total"] for f in flights),
        "collisions": sum(f.summary["collisions"] for f in flights),
        "min_clearance_m": min(clear) if clear else None,
        "px4_setpoint_rate_hz": _median(setpoint_hz),
        "e2e_latency_ms_p95": round(float(np.percentile(e2e_ms, 95)), 1) if e2e_ms else None,
        "e2e_latency_ms_p50": round(float(np.percentile(e2e_ms, 50)), 1) if e2e_ms else None,
        "e2e_latency_samples": len(e2e_ms),
        "load_avg_1min": [round(load0[0], 1), round(load1[0], 1)],
        "obstacle_distance_rate_hz": _median(obstacle_hz),
        "scenarios": scenarios,
    }
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
