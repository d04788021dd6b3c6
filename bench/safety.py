"""The safety benchmark: closed-loop flights through furnished rooms with the metric-only and
the semantic map, judged against the true geometry.

Run: ``python bench/safety.py`` (50 rooms), ``--rooms N --seed S`` to scale it, ``--quick`` for a
small version (2 rooms, under a minute on an idle machine).

Each room (``bench/_safety_scenarios.py``) has a start and a goal whose straight line crosses
hollow-bottom furniture: at 0.6 m (``blocking``: desk tops, table tops and chair seats reach
into the vehicle's band, a depth slice sees their legs) or at 1.5 m (``overflight``: the
furniture stays below the band and may be flown over). Every room is flown twice through the
whole pipeline - rendered RGB-D frames, the detector (``--detector``), the BoT-SORT tracker, the
semantic map, the planner, the setpoint stream as MAVLink into the mock PX4 - once with
``map.mode: metric`` (the occupancy grid of a thin depth slice at flight altitude, what a plain
2D map gives) and once with ``map.mode: semantic``. The flights run in lock-step simulated
time with compute time charged where the service would wait for it (``bench/_safety_loop.py``).

Judged against the true boxes (``bench/_judge.py``): collision with the vertical margin
(the vehicle's radius and height stretched by ``planner.vertical_margin_m`` above and below:
grazing under a table top counts) and exact; success (goal within 0.3 m before the time limit);
path length, time and minimum clearance. Per-stage latencies are wall-clock on this machine,
beside the reference design's Jetson Xavier AGX figures. The map-update kernels are compiled
(or loaded from numba's cache) before the first flight, as the service does at start, so the
stage maxima are those of flight frames, not of a one-off compile (about 9 s on a fresh clone).

Writes ``results.json`` and PNGs into ``--out`` (default ``bench/out/safety``); ``--readme``
also writes the example picture and the chart into ``docs/images/``. The last line printed is
one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._judge import FlightVerdict, judge_flight, side_clearance_m  # noqa: E402
from bench._safety_loop import FlightLog, LockstepFlight  # noqa: E402
from bench._safety_plots import clearance_histogram, example_room, rates_chart  # noqa: E402
from bench._safety_scenarios import Scenario, make_scenarios  # noqa: E402
from companion.config import CompanionConfig, load_config  # noqa: E402
from companion.sim.groundtruth import densify  # noqa: E402
from companion.sim.render import renderer_from_config  # noqa: E402
from companion.sim.world import LAYOUTS  # noqa: E402
from semmap.costmap import VerticalBand  # noqa: E402
from semmap.detection import Detector, detector_from_config  # noqa: E402
from semmap.kernels import warm_up  # noqa: E402

MAPS = ("metric", "semantic")
#: The reference design's per-stage figures on a Jetson Xavier AGX (ms).
REFERENCE_MS = {"detect": 250.0, "pointcloud": 500.0}
#: Latency table rows: (key, label, where the figure comes from).
STAGES = (
    ("detect", "detection", "detector on one frame"),
    ("track", "tracking", "BoT-SORT incl. camera-motion compensation"),
    ("pointcloud", "point-cloud processing", "object geometry: back-projection, clusters, planes"),
    ("grid", "grid", "depth band scan into the grid + layers"),
    ("costmap", "costmap", "combined costmap at the flight band"),
    ("plan", "planning", "one planner request (first path + refinement budget)"),
    ("replan", "  re-planning in flight", "a re-plan request (planner.replan_time_limit_s budget)"),
    ("plan_first", "planning, first path", "map preparation + first valid path"),
    ("check", "path check", "remaining path against the new map"),
    ("e2e", "end-to-end", "frame handed to perception -> setpoint on a map that includes it"),
    ("e2e_keep", "  path still free", "end-to-end for frames after which the path stays valid"),
    ("e2e_replan", "  re-planned", "end-to-end for frames that made the path invalid (+ one re-plan)"),
    ("e2e_hold", "  planned from a hold", "a leg's first plan or a retry while holding (+ one full request)"),
)
ACCEPTANCE_M = 0.3


def progress(done: int, total: int, t0: float, note: str) -> None:
    """A one-line progress bar on stderr (stdout stays for the table and the JSON)."""
    width = 30
    k = int(width * done / max(total, 1))
    elapsed = time.monotonic() - t0
    eta = elapsed / done * (total - done) if done else float("nan")
    eta_txt = f"{eta / 60:4.1f} min left" if math.isfinite(eta) else "          "
    sys.stderr.write(f"\r[{'#' * k}{'.' * (width - k)}] {done}/{total} flights, {elapsed / 60:4.1f} min, "
                     f"{eta_txt} {note[:40]:<40}")
    sys.stderr.flush()
    if done == total:
        sys.stderr.write("\n")


def make_detector(cfg: CompanionConfig, which: str, scenario: Scenario) -> tuple[Detector, CompanionConfig]:
    """The detector for a room: the shipped model (``builtin:NAME``, loaded once by the caller's
    cache) or the simulator's oracle (knows the room's objects)."""
    names = [c.name for c in cfg.classes]
    if which == "oracle":
        dcfg = cfg.detector.model_copy(update={"kind": "oracle"})
        det = detector_from_config(dcfg, names, object_classes={o.object_id: o.class_name
                                                                for o in scenario.room.objects},
                                   seed=scenario.room.seed)
        return det, cfg.model_copy(update={"detector": dcfg})
    dcfg = cfg.detector.model_copy(update={"kind": "onnx", "model_path": which})
    return detector_from_config(dcfg, names), cfg.model_copy(update={"detector": dcfg})


def time_limit_s(scenario: Scenario, cfg: CompanionConfig) -> float:
    """The leg's time limit: 10 s plus three times the straight line at full speed."""
    return 10.0 + 3.0 * scenario.distance_m / cfg.planner.max_speed_m_s


def fly_room(cfg: CompanionConfig, scenario: Scenario, detector_name: str, det_cache: dict[str, Any],
             args: argparse.Namespace) -> list[tuple[str, FlightLog, LockstepFlight]]:
    """The flights of one room (``args.maps``: metric-only first, then semantic), sharing the
    renderer."""
    renderer = renderer_from_config(scenario.room, cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"seed": scenario.room.seed})}))
    out = []
    try:
        for mode in args.maps:
            if detector_name == "oracle":
                det, _ = make_detector(cfg, "oracle", scenario)
            else:
                if "det" not in det_cache:
                    det_cache["det"], _ = make_detector(cfg, detector_name, scenario)
                det = det_cache["det"]
            flight = LockstepFlight(cfg, scenario, mode, det, detector_name, renderer,
                                    perception_hz=args.perception_hz, check_period_s=args.check_period_s,
                                    metric_slice_m=args.metric_slice_m, time_limit_s=time_limit_s(scenario, cfg))
            out.append((mode, flight.run(), flight))
    finally:
        renderer.close()
    return out


def judge(cfg: CompanionConfig, scenario: Scenario, flight: LockstepFlight) -> tuple[FlightVerdict, np.ndarray]:
    """The verdict and the (M, 3) room-frame collision points (with the margin) of one flight."""
    p = cfg.planner
    xyz, t = flight.trajectory_room()
    if len(xyz) == 0:
        xyz = flight.placement.map_to_room(np.asarray(flight.log.xyz_map_m, dtype=np.float64).reshape(-1, 3)[-1:])
        t = np.asarray(flight.log.t_s[-1:])
    v = judge_flight(scenario.room, xyz, t, scenario.goal_xy_m, vehicle_radius_m=p.vehicle_radius_m,
                     vehicle_height_m=p.vehicle_height_m, vertical_margin_m=p.vertical_margin_m,
                     acceptance_m=ACCEPTANCE_M, time_limit_s=time_limit_s(scenario, cfg))
    hits = np.zeros((0, 3))
    if v.collided:
        dense = densify(xyz, 0.02)
        extent = p.vehicle_height_m + 2.0 * p.vertical_margin_m
        hits = dense[side_clearance_m(scenario.room, dense, p.vehicle_radius_m, extent) < 0.0]
    return v, hits


def pct(values: list[float | None], q: float) -> float | None:
    """The ``q``-th percentile of the finite values (None when there are none)."""
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return round(float(np.percentile(vals, q)), 3) if vals else None


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Figures of a set of flights of one map type."""
    n = len(records)
    if n == 0:
        return {"flights": 0}

    def rate(key: str) -> float:
        return round(100.0 * sum(1 for r in records if r[key]) / n, 1)

    ok = [r for r in records if r["reached"]]
    return {
        "flights": n,
        "collisions": sum(1 for r in records if r["collided"]),
        "collisions_exact": sum(1 for r in records if r["collided_exact"]),
        "collision_rate_pct": rate("collided"),
        "collision_exact_rate_pct": rate("collided_exact"),
        "success_rate_pct": rate("success"),
        "safe_success_rate_pct": rate("safe_success"),
        "path_length_m_median": pct([r["path_length_m"] for r in ok], 50),
        # Flown length over the straight line to the acceptance circle (1.0 = straight).
        "path_over_straight_median": pct([r["path_length_m"] / max(r["straight_m"] - ACCEPTANCE_M, 0.1)
                                          for r in ok], 50),
        "time_s_median": pct([r["time_s"] for r in ok], 50),
        "min_clearance_m_p5": pct([r["min_clearance_m"] for r in records], 5),
        "min_clearance_m_median": pct([r["min_clearance_m"] for r in records], 50),
        "min_object_clearance_m_median": pct([r["min_object_clearance_m"] for r in records], 50),
        "replans_mean": round(float(np.mean([r["replans"] for r in records])), 2),
    }


def latency_table(logs: list[FlightLog]) -> dict[str, dict[str, float | int | None]]:
    """p50/p95/max (ms) and sample counts of every stage over all flights."""
    samples: dict[str, list[float]] = {k: [] for k, _, _ in STAGES}
    for lg in logs:
        for f in lg.frames:
            for k, v in f.stages_ms.items():
                samples["pointcloud" if k == "geometry" else k].append(v)
            samples["costmap"].append(f.costmap_ms)
            if f.e2e_ms is not None:
                samples["e2e"].append(f.e2e_ms)
                key = "e2e_replan" if f.replanned else "e2e_hold" if f.from_hold else "e2e_keep"
                samples[key].append(f.e2e_ms)
        samples["plan"].extend(lg.plan_ms)
        samples["replan"].extend(lg.replan_ms)
        samples["plan_first"].extend(lg.plan_first_ms)
        samples["check"].extend(lg.check_ms)
    return {k: {"p50_ms": pct(v, 50), "p95_ms": pct(v, 95), "max_ms": pct(v, 100), "count": len(v)}
            for k, v in samples.items()}


def print_report(fig: dict[str, Any]) -> None:
    """The readable tables."""
    print(f"\nsafety bench: {fig['rooms']} {fig['world']} rooms (seeds from {fig['seed']}), detector {fig['detector']}, "
          f"{fig['flights']} flights, {fig['wall_s'] / 60:.1f} min wall for {fig['sim_s'] / 60:.1f} min flown")
    print(f"judged with the vehicle radius {fig['judge']['vehicle_radius_m']} m, height "
          f"{fig['judge']['vehicle_height_m']} m and vertical margin {fig['judge']['vertical_margin_m']} m; "
          f"metric-only map = a {fig['config']['metric_slice_m']} m depth slice at flight altitude\n")
    head = (f"{'case':<22} {'flights':>7} {'coll.':>6} {'coll.%':>7} {'exact%':>7} {'success%':>9} "
            f"{'safe%':>6} {'len/straight':>12} {'time s':>7} {'clear p5 m':>10} {'clear med m':>11}")
    print(head)
    print("-" * len(head))
    for case in ("all", "blocking", "overflight"):
        for m in MAPS:
            s = fig[m] if case == "all" else fig[m]["by_kind"].get(case, {"flights": 0})
            if not s.get("flights"):
                continue

            def f(key: str, fmt: str = "{:.2f}", s: dict[str, Any] = s) -> str:
                v = s.get(key)
                return "-" if v is None else fmt.format(v)
            print(f"{case + ' / ' + m:<22} {s['flights']:>7} {s['collisions']:>6} {f('collision_rate_pct', '{:.1f}'):>7} "
                  f"{f('collision_exact_rate_pct', '{:.1f}'):>7} {f('success_rate_pct', '{:.1f}'):>9} "
                  f"{f('safe_success_rate_pct', '{:.0f}'):>6} {f('path_over_straight_median'):>12} "
                  f"{f('time_s_median', '{:.1f}'):>7} {f('min_clearance_m_p5'):>10} {f('min_clearance_m_median'):>11}")
    print("\nper-stage latency on this machine (wall clock, ms) beside the reference design on a Jetson Xavier AGX")
    print(f"(map-update kernels compiled or loaded before the first flight: {fig['kernel_warm_up_s']:.2f} s, not counted)")
    head = f"{'stage':<24} {'p50':>8} {'p95':>8} {'max':>8} {'n':>6} {'Xavier AGX':>11}  what"
    print(head)
    print("-" * (len(head) + 40))
    for key, label, what in STAGES:
        s = fig["latency_ms"][key]

        def g(v: float | None) -> str:
            return "-" if v is None else f"{v:.1f}"
        ref = REFERENCE_MS.get(key)
        print(f"{label:<24} {g(s['p50_ms']):>8} {g(s['p95_ms']):>8} {g(s['max_ms']):>8} {s['count']:>6} "
              f"{'-' if ref is None else f'{ref:.0f}':>11}  {what}")
    if fig["semantic_failures"]:
        print("\nsemantic-map flights that collided or failed:")
        for r in fig["semantic_failures"]:
            print(f"  room {r['room_seed']} ({r['kind']}, {r['altitude_m']} m): collided {r['collided']} "
                  f"(objects {r['hit_object_ids']}), reached {r['reached']}, error {r['error']}")


def _owner_name(room: Any, owner: int) -> str:
    """What a judged collision hit: a class, ``wall``, or the clutter's kind (``clutter:plant``)."""
    if owner == 0:
        return "wall"
    if owner < 0:
        return "clutter:" + next((c.class_name for c in room.clutter if c.object_id == owner), "?")
    return str(room.object_by_id(owner).class_name)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 rooms (one at each altitude), under a minute idle")
    ap.add_argument("--rooms", type=int, default=None, help="rooms to fly (default 50; each is flown twice)")
    ap.add_argument("--seed", type=int, default=1000, help="first room seed")
    ap.add_argument("--detector", default="builtin:furniture",
                    help="builtin:NAME (a shipped ONNX model, default builtin:furniture), a .onnx path, or oracle")
    ap.add_argument("--altitudes", type=lambda v: [float(x) for x in v.split(",")], default=None,
                    help="flight altitudes cycled over the rooms (default 0.6,0.6,1.5; --quick 0.6,1.5)")
    ap.add_argument("--perception-hz", type=float, default=4.0,
                    help="at most this many frames per simulated second go through perception (default 4)")
    ap.add_argument("--check-period-s", type=float, default=0.0,
                    help="check the remaining path this often (0 = on every new map; the service's runner: 0.5)")
    ap.add_argument("--metric-slice-m", type=float, default=0.1,
                    help="thickness of the depth slice the metric-only map is built from (default 0.1 m)")
    ap.add_argument("--maps", type=_maps_arg, default=list(MAPS),
                    help="map types to fly, comma-separated (default metric,semantic; one alone for diagnosis)")
    ap.add_argument("--only", type=lambda v: {int(x) for x in v.split(",")}, default=None,
                    help="fly only these room seeds (comma-separated) of the --rooms/--seed set, e.g. the failures")
    ap.add_argument("--config", default=None, help="config file (default: the embedded default)")
    ap.add_argument("--world", choices=LAYOUTS, default=None,
                    help="room layout (default: the config's sim.layout, realistic)")
    ap.add_argument("--out", default=str(REPO / "bench" / "out" / "safety"), help="output folder")
    ap.add_argument("--readme", action="store_true", help="also write the pictures for the README into docs/images/")
    ap.add_argument("-v", "--verbose", action="store_true", help="log the flights")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rooms = args.rooms if args.rooms is not None else (2 if args.quick else 50)
    altitudes = args.altitudes or ([0.6, 1.5] if args.quick else [0.6, 0.6, 1.5])
    cfg = load_config(args.config) if args.config else CompanionConfig()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    kernels_s = warm_up()
    world = args.world or cfg.sim.layout
    scenarios = make_scenarios(cfg, rooms, args.seed, altitudes, layout=world)
    if len(scenarios) < rooms:
        print(f"only {len(scenarios)} of {rooms} rooms had a fitting start and goal", file=sys.stderr)
    if args.only is not None:
        unknown = args.only - {sc.room.seed for sc in scenarios}
        if unknown:
            ap.error(f"--only: room seeds {sorted(unknown)} are not among the {len(scenarios)} rooms from seed {args.seed}")
        scenarios = [sc for sc in scenarios if sc.room.seed in args.only]
    records: list[dict[str, Any]] = []
    logs: list[FlightLog] = []
    kept: dict[int, dict[str, Any]] = {}
    det_cache: dict[str, Any] = {}
    total = len(args.maps) * len(scenarios)
    progress(0, total, t0, "")
    for sc in scenarios:
        for mode, lg, flight in fly_room(cfg, sc, args.detector, det_cache, args):
            v, hits = judge(cfg, sc, flight)
            logs.append(lg)
            xyz, _t = flight.trajectory_room()
            kept.setdefault(sc.index, {"scenario": sc})[mode] = (xyz[::5], hits, v)
            records.append({
                "room_seed": sc.room.seed, "kind": sc.kind, "altitude_m": sc.altitude_m, "map": mode,
                "straight_m": round(sc.distance_m, 3), "crossed": [c for _, c in sc.crossed],
                "collided": v.collided, "collided_exact": v.collided_exact, "hit_object_ids": list(v.hit_object_ids),
                "hit_classes": [_owner_name(sc.room, i) for i in v.hit_object_ids],
                "reached": v.reached, "success": v.success, "safe_success": v.safe_success,
                "time_s": round(v.time_s, 2), "path_length_m": round(v.path_length_m, 3),
                "min_clearance_m": round(v.min_clearance_m, 3),
                "min_object_clearance_m": round(v.min_object_clearance_m, 3)
                if math.isfinite(v.min_object_clearance_m) else None,
                "plans": lg.plans, "replans": lg.replans_invalid, "failed_plans": lg.failed_plans,
                "frames": len(lg.frames), "objects_mapped": len(lg.objects_mapped),
                "sim_s": round(lg.sim_s, 2), "wall_s": round(lg.wall_s, 2), "error": lg.error,
            })
            progress(len(records), total, t0, f"room {sc.room.seed} {mode}: "
                     f"{'COLLIDED' if v.collided else 'ok'}, {'reached' if v.reached else 'NOT reached'}")
    fig: dict[str, Any] = {
        "world": world, "rooms": len(scenarios), "seed": args.seed, "detector": args.detector, "flights": len(records),
        "wall_s": round(time.monotonic() - t0, 1), "kernel_warm_up_s": round(kernels_s, 2), "sim_s": round(sum(r["sim_s"] for r in records), 1),
        "judge": {"vehicle_radius_m": cfg.planner.vehicle_radius_m, "vehicle_height_m": cfg.planner.vehicle_height_m,
                  "vertical_margin_m": cfg.planner.vertical_margin_m, "acceptance_m": ACCEPTANCE_M},
        "config": {"altitudes_m": altitudes, "perception_hz": args.perception_hz,
                   "check_period_s": args.check_period_s, "metric_slice_m": args.metric_slice_m,
                   "planner_time_limit_s": cfg.planner.time_limit_s},
    }
    for m in MAPS:
        mine = [r for r in records if r["map"] == m]
        fig[m] = summarize(mine)
        fig[m]["by_kind"] = {k: summarize([r for r in mine if r["kind"] == k]) for k in ("blocking", "overflight")}
    fig["latency_ms"] = latency_table(logs)
    # The names for the headline figures.
    fig["semantic"]["success_rate"] = round(fig["semantic"].get("success_rate_pct", 0.0) / 100.0, 3)
    fig["metric_only"] = {"collisions": fig["metric"].get("collisions", 0)}
    fig["e2e_latency_ms_p95"] = fig["latency_ms"]["e2e"]["p95_ms"]
    fig["reference_jetson_xavier_agx_ms"] = REFERENCE_MS
    fig["semantic_failures"] = [r for r in records if r["map"] == "semantic" and not r["safe_success"]]
    # The pictures compare the two maps: only drawn when both were flown.
    fig["pictures"] = write_pictures(out, cfg, fig, records, kept, args.readme) if len(args.maps) == 2 else {}
    (out / "results.json").write_text(json.dumps({**fig, "flights_detail": records}, indent=1) + "\n",
                                      encoding="utf-8")
    print_report(fig)
    print(f"\nresults: {out / 'results.json'}; pictures: {', '.join(fig['pictures'].values())}")
    print(json.dumps(fig, sort_keys=True, default=float))
    return 0


def _maps_arg(value: str) -> list[str]:
    maps = [m.strip() for m in value.split(",") if m.strip()]
    bad = [m for m in maps if m not in MAPS]
    if bad or not maps:
        raise argparse.ArgumentTypeError(f"--maps: {bad or value!r} not among {', '.join(MAPS)}")
    return [m for m in MAPS if m in maps]


def write_pictures(out: Path, cfg: CompanionConfig, fig: dict[str, Any], records: list[dict[str, Any]],
                   kept: dict[int, dict[str, Any]], readme: bool) -> dict[str, str]:
    """The chart, the histogram and the example room; copies for the README with ``readme``."""
    groups = [("all flights", {m: fig[m] for m in MAPS})]
    for kind in ("blocking", "overflight"):
        if fig["metric"]["by_kind"].get(kind, {}).get("flights"):
            alts = sorted({r["altitude_m"] for r in records if r["kind"] == kind})
            groups.append((f"{kind} ({', '.join(f'{a} m' for a in alts)})",
                           {m: fig[m]["by_kind"][kind] for m in MAPS}))
    files = {"rates": rates_chart(out / "safety_rates.png", groups)}
    files["clearance"] = clearance_histogram(out / "safety_clearance.png", {
        m: [r["min_clearance_m"] for r in records if r["map"] == m] for m in MAPS})
    # The example: a blocking room where the metric-only flight collided and the semantic one
    # reached the goal safely (the reference design's figure), else the first blocking room.
    def score(entry: dict[str, Any]) -> int:
        sc: Scenario = entry["scenario"]
        if "metric" not in entry or "semantic" not in entry:
            return -1
        vm, vs = entry["metric"][2], entry["semantic"][2]
        return 2 * int(sc.kind == "blocking") + 2 * int(vm.collided) + 2 * int(vs.safe_success) + \
            int(any(c in ("desk", "coffee_table", "conference_table") for _, c in sc.crossed))
    if kept:
        best = max(kept.values(), key=score)
        sc = best["scenario"]
        band = cfg.planner.band_at(sc.altitude_m)
        slice_band = VerticalBand(sc.altitude_m - fig["config"]["metric_slice_m"] / 2,
                                  sc.altitude_m + fig["config"]["metric_slice_m"] / 2)
        title = (f"room seed {sc.room.seed} at {sc.altitude_m} m: metric-only "
                 f"{'COLLIDED' if best['metric'][2].collided else 'no collision'}, semantic "
                 f"{'COLLIDED' if best['semantic'][2].collided else 'no collision'}"
                 f"{'' if best['semantic'][2].reached else ' (not reached)'}")
        files["example"] = example_room(out / "safety_example.png", sc.room, band, slice_band,
                                        {m: best[m][0] for m in MAPS if m in best}, sc.start_xy_m, sc.goal_xy_m,
                                        {m: best[m][1] for m in MAPS if m in best}, title)
    if readme:
        images = REPO / "docs" / "images"
        images.mkdir(parents=True, exist_ok=True)
        for key in ("example", "rates"):
            if key in files:
                shutil.copyfile(files[key], images / files[key].name)
    return {k: str(v) for k, v in files.items()}


if __name__ == "__main__":
    sys.exit(main())
