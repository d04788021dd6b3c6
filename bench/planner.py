"""Planner on seeded simulated rooms: speed, path quality, safety, replanning, metric-only maps.

Run: ``python bench/planner.py`` (50 rooms of 20 x 20 m at 5 cm, 30 objects each) or
``--quick`` (4 rooms of 12 x 12 m, under a minute on an idle machine).

Per room, two queries at the configured flight altitude: doorway to doorway, and two random
free points far apart whose straight line crosses hollow-bottom furniture. For each query:

* **semantic**: the planner on the ideal semantic costmap (ground truth: walls, what a depth
  slice sees, and the whole footprint of every object that blocks the vehicle's band).
  ``first_path_ms``: time from the request until a valid path exists, on a map whose fields
  are prepared (``prepare_ms`` is that preparation, done once per map version;
  ``first_path_incl_prepare_ms`` adds it, i.e. a request on a brand-new map). ``planning_ms``:
  the whole request including OMPL's improvement within the time budget.
* **reference**: the shortest path on the same inflated map, computed in the same run by an
  independent search: full-resolution 8-connected Dijkstra on path length only, then
  any-angle shortcutting and corner sliding. ``length_ratio`` = planner length / reference.
* **collisions**: every final path is judged against the true box geometry
  (``groundtruth.path_collides``) for the vehicle's radius and height.
* **replan**: a desk is put across the path's middle; the planner takes the new map version
  (windowed update) and replans from the start. ``replan_ms`` = map update + time to the
  first valid path; the new path is judged against the room with the desk.
* **metric_only**: the same queries planned on a metric-only map (a thin depth slice at the
  flight altitude, no objects): how many of those paths hit furniture the slice cannot see.

The last line printed is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.sim import groundtruth as gt  # noqa: E402
from companion.sim.world import Box, FurnitureObject, Room, generate_room  # noqa: E402
from planner.config import PlannerConfig  # noqa: E402
from planner.cspace import CSpace  # noqa: E402
from planner.gridsearch import GridGraph, refine_vertices, shortcut  # noqa: E402
from planner.ompl_backend import set_ompl_seed  # noqa: E402
from planner.planner import Planner  # noqa: E402
from planner.types import path_length_m  # noqa: E402
from semmap.grid import rasterize_polygon  # noqa: E402

HOLLOW_CLASSES = ("chair", "coffee_table", "conference_table", "desk", "whiteboard")


@dataclass
class Query:
    room_seed: int
    kind: str
    start: np.ndarray
    goal: np.ndarray


def reference_path(cs: CSpace, start: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Shortest path on the inflated map (length only, full resolution, any-angle)."""
    t0 = time.perf_counter()
    g = GridGraph(cs, cost_weight=0.0, factor=1)
    out = g.search(start, goal)
    if out.path_xy_m is None:
        return None, time.perf_counter() - t0
    p = refine_vertices(cs, shortcut(cs, out.path_xy_m, 0.0), 0.0, rounds=8)
    return p, time.perf_counter() - t0


def pick_queries(room: Room, cs: CSpace, rng: np.random.Generator) -> list[Query]:
    """Doorway to doorway, plus free points far apart whose chord crosses hollow furniture
    that blocks the flight band."""
    out: list[Query] = []
    if len(room.doorways) >= 2:
        s = np.array(room.doorways[0].inside_point_m(0.7))
        g = np.array(room.doorways[1].inside_point_m(0.7))
        if cs.is_free(np.array([s, g])).all():
            out.append(Query(room.seed, "doorways", s, g))
    # Hollow-bottom objects that block the vehicle's band: a metric slice sees only their legs.
    hollow = [fp.polygon_xy_m for fp in gt.object_footprints(room)
              if fp.class_name in HOLLOW_CLASSES and fp.blocks(cs.band)]
    masks = np.zeros(cs.spec.shape_rc, dtype=bool)
    for poly in hollow:
        masks |= rasterize_polygon(cs.spec, poly)
    min_dist = 0.45 * min(room.width_m, room.depth_m)
    for _ in range(400):
        pts = rng.uniform([0.3, 0.3], [room.width_m - 0.3, room.depth_m - 0.3], size=(2, 2))
        if np.linalg.norm(pts[1] - pts[0]) < min_dist or not cs.is_free(pts).all():
            continue
        chord = cs.sample_segment(pts[0], pts[1])
        rc, inside = cs.cells(chord)
        if masks[rc[inside, 0], rc[inside, 1]].any():
            out.append(Query(room.seed, "crossing", pts[0], pts[1]))
            break
    return out


def _xyz(path: np.ndarray, z: float) -> np.ndarray:
    return np.column_stack([path, np.full(len(path), z)])


def add_desk_across(room: Room, path: np.ndarray, start: np.ndarray, goal: np.ndarray) -> Room | None:
    """The room with a desk centred on the path's middle, across it; None if none fits."""
    dense = gt.densify(path, 0.05)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    for frac in (0.5, 0.4, 0.6, 0.3, 0.7):
        k = int(np.searchsorted(s, frac * s[-1]))
        k = min(max(k, 1), len(dense) - 1)
        c = dense[k]
        if min(np.linalg.norm(c - start), np.linalg.norm(c - goal)) < 1.6:
            continue
        d = dense[k] - dense[k - 1]
        yaw = math.atan2(d[1], d[0]) + math.pi / 2  # desk's long side across the path
        L, W, H, t = 1.4, 0.7, 0.75, 0.03
        cs_, sn = math.cos(yaw), math.sin(yaw)
        parts = [Box((float(c[0]), float(c[1]), H - t / 2), (L, W, t), yaw)]
        for sx in (-1, 1):
            for sy in (-1, 1):
                lx, ly = sx * (L / 2 - 0.06), sy * (W / 2 - 0.06)
                parts.append(Box((float(c[0] + cs_ * lx - sn * ly), float(c[1] + sn * lx + cs_ * ly), (H - t) / 2),
                                 (0.05, 0.05, H - t), yaw))
        obj = FurnitureObject(
            object_id=max((o.object_id for o in room.objects), default=0) + 1, class_name="desk",
            center_xy_m=(float(c[0]), float(c[1])), yaw_rad=yaw, size_m=(L, W, H), parts=tuple(parts),
            color_rgb=(70, 240, 240),
        )
        return replace(room, objects=(*room.objects, obj))
    return None


def altitude_sweep(room: Room, spec: Any, cfg: PlannerConfig, queries: list[Query],
                   altitudes: list[float], tallies: dict[float, dict[str, int]]) -> None:
    """Semantic vs metric-only map at several altitudes: paths that hit the true geometry.

    Judged twice: with the vehicle's height (exact) and with its planning band (height plus
    the vertical margin above and below), i.e. "passes closer than the margin".
    """
    r, h = cfg.vehicle_radius_m, cfg.vehicle_height_m
    h_band = h + 2.0 * cfg.vertical_margin_m
    for alt in altitudes:
        c = cfg.model_copy(update={"flight_altitude_m": alt, "refine_with_ompl": False})
        sem, met = Planner(c), Planner(c)
        sem.set_map(gt.semantic_costmap(room, spec, sem.band))
        met.set_map(gt.metric_costmap(room, spec, alt))
        t = tallies.setdefault(alt, {k: 0 for k in (
            "queries", "semantic_paths", "semantic_collisions", "semantic_margin_violations",
            "metric_paths", "metric_collisions", "metric_margin_violations")})
        for q in queries:
            t["queries"] += 1
            for name, pl in (("semantic", sem), ("metric", met)):
                res = pl.plan(q.start, q.goal)
                if not res.ok:
                    continue
                t[f"{name}_paths"] += 1
                xyz = _xyz(res.path_xy_m, alt)
                t[f"{name}_collisions"] += int(gt.path_collides(room, xyz, r, h))
                t[f"{name}_margin_violations"] += int(gt.path_collides(room, xyz, r, h_band))


def save_picture(path: Path, planner: Planner, costmap: Any, res: Any, metric: Any, q: Query) -> None:
    """The semantic plan (blue) and the metric-only plan (orange) over the semantic costmap."""
    import cv2

    from companion.cli.plan import draw_plan

    img = draw_plan(planner, costmap, res, (float(q.start[0]), float(q.start[1])),
                    (float(q.goal[0]), float(q.goal[1])))
    if metric.ok:
        spec = costmap.spec
        scale = max(1, int(np.ceil(700 / max(spec.shape_rc))))
        xy = metric.path_xy_m
        col = (xy[:, 0] - spec.origin_xy_m[0]) / spec.resolution_m * scale
        row = 26 + spec.rows * scale - (xy[:, 1] - spec.origin_xy_m[1]) / spec.resolution_m * scale
        pts = np.round(np.stack([col, row], axis=1)).astype(np.int32)
        cv2.polylines(img, [pts], False, (0, 140, 255), 2, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def run(args: argparse.Namespace) -> dict[str, Any]:
    updates: dict[str, Any] = dict(kv.split("=", 1) for kv in args.set)
    if args.time_limit_s:
        updates["time_limit_s"] = args.time_limit_s
    if args.altitude_m:
        updates["flight_altitude_m"] = args.altitude_m
    cfg = PlannerConfig.model_validate(updates)
    set_ompl_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    z, r, h = cfg.flight_altitude_m, cfg.vehicle_radius_m, cfg.vehicle_height_m
    sem: dict[str, list[float]] = {k: [] for k in ("first", "first_prep", "prep", "total", "ratio", "ref_ms")}
    counts = {"queries": 0, "sem_ok": 0, "sem_collide": 0, "sem_no_path": 0, "ompl_improved": 0,
              "replan_cases": 0, "replan_ok": 0, "replan_collide": 0, "replan_no_path": 0,
              "metric_ok": 0, "metric_collide": 0, "metric_collide_objects": 0, "metric_margin": 0, "ref_missing": 0}
    replan_ms: list[float] = []
    sweep: dict[float, dict[str, int]] = {}
    n_pictures = 0
    rows: list[str] = []
    t_start = time.perf_counter()
    for i in range(args.rooms):
        seed = args.seed + i
        room = generate_room(seed, width_m=args.size_m, depth_m=args.size_m, n_objects=args.objects)
        spec = gt.room_grid_spec(room, 0.05)
        planner = Planner(cfg)
        semantic = gt.semantic_costmap(room, spec, planner.band)
        planner.set_map(semantic)
        prep_s = planner.last_prepare_s
        metric = Planner(cfg)
        metric.set_map(gt.metric_costmap(room, spec, z))
        queries = pick_queries(room, planner.cspace, rng)
        altitude_sweep(room, spec, cfg, queries, args.altitudes, sweep)
        for q in queries:
            counts["queries"] += 1
            res = planner.plan(q.start, q.goal)
            ref, ref_s = reference_path(planner.cspace, q.start, q.goal)
            sem["ref_ms"].append(ref_s * 1e3)
            if not res.ok:
                counts["sem_no_path"] += 1
                rows.append(f"{seed:5d} {q.kind:9s} no path: {res.status.value} ({res.reason})")
                continue
            counts["sem_ok"] += 1
            counts["ompl_improved"] += int(res.stats.get("ompl_improved", 0.0) > 0)
            sem["first"].append(res.first_solution_time_s * 1e3)
            sem["prep"].append(prep_s * 1e3)
            sem["first_prep"].append((prep_s + res.first_solution_time_s) * 1e3)
            sem["total"].append(res.planning_time_s * 1e3)
            collide = gt.path_collides(room, _xyz(res.path_xy_m, z), r, h)
            counts["sem_collide"] += int(collide)
            ratio = float("nan")
            if ref is not None:
                ratio = res.length_m / path_length_m(ref)
                sem["ratio"].append(ratio)
            else:
                counts["ref_missing"] += 1
            # Metric-only map: same query.
            m = metric.plan(q.start, q.goal)
            if args.pictures and n_pictures < 6:
                n_pictures += 1
                save_picture(Path(args.pictures) / f"room{seed}_{q.kind}.png", planner, semantic, res, m, q)
            m_collide = False
            if m.ok:
                counts["metric_ok"] += 1
                xyz = _xyz(m.path_xy_m, z)
                m_collide = gt.path_collides(room, xyz, r, h)
                counts["metric_collide"] += int(m_collide)
                objs = gt.clearance_m(room, gt.densify(xyz, 0.02), h, include_walls=False) < r
                counts["metric_collide_objects"] += int(bool(objs.any()))
                counts["metric_margin"] += int(gt.path_collides(room, xyz, r, h + 2 * cfg.vertical_margin_m))
            # Replanning after a desk appears across the path.
            rp_text = "-"
            new_room = add_desk_across(room, res.path_xy_m, q.start, q.goal)
            if new_room is not None:
                counts["replan_cases"] += 1
                new_map = gt.semantic_costmap(new_room, spec, planner.band)
                t0 = time.perf_counter()
                planner.set_map(new_map)
                update_s = time.perf_counter() - t0
                still = planner.path_still_valid(res.path_xy_m)
                rp = planner.plan(q.start, q.goal) if not still else res
                if rp.ok:
                    counts["replan_ok"] += 1
                    ms = (update_s + (rp.first_solution_time_s if not still else 0.0)) * 1e3
                    replan_ms.append(ms)
                    rc = gt.path_collides(new_room, _xyz(rp.path_xy_m, z), r, h)
                    counts["replan_collide"] += int(rc)
                    rp_text = f"{ms:6.1f}{' HIT' if rc else ''}"
                else:
                    counts["replan_no_path"] += 1
                    rp_text = rp.status.value
                planner.set_map(semantic)  # back to the room without the desk
            rows.append(
                f"{seed:5d} {q.kind:9s} {res.first_solution_time_s * 1e3:7.1f} {res.planning_time_s * 1e3:7.1f} "
                f"{res.length_m:7.2f} {ratio:6.3f} {res.source:24s} {'HIT' if collide else 'ok':4s} "
                f"{rp_text:>9s} {('HIT' if m_collide else 'ok') if m.ok else m.status.value:>12s}"
            )
    wall_s = time.perf_counter() - t_start
    ratios = sem["ratio"]
    figures = {
        "rooms": args.rooms, "room_size_m": args.size_m, "objects_per_room": args.objects,
        "queries": counts["queries"], "time_limit_s": cfg.time_limit_s, "algorithm": cfg.algorithm,
        "semantic": {
            "paths": counts["sem_ok"], "no_path": counts["sem_no_path"],
            "first_path_ms_p50": pct(sem["first"], 50), "first_path_ms_p95": pct(sem["first"], 95),
            "first_path_incl_prepare_ms_p95": pct(sem["first_prep"], 95),
            "prepare_ms_p95": pct(sem["prep"], 95),
            "planning_ms_p50": pct(sem["total"], 50), "planning_ms_p95": pct(sem["total"], 95),
            "length_ratio_p50": pct(ratios, 50), "length_ratio_p95": pct(ratios, 95),
            "length_ratio_max": float(max(ratios)) if ratios else float("nan"),
            "length_within_5pct_frac": float(np.mean(np.array(ratios) <= 1.05)) if ratios else float("nan"),
            "collisions": counts["sem_collide"],
            "ompl_improved_frac": counts["ompl_improved"] / max(counts["sem_ok"], 1),
        },
        "reference": {"ms_p50": pct(sem["ref_ms"], 50), "missing": counts["ref_missing"]},
        "replan": {
            "cases": counts["replan_cases"], "paths": counts["replan_ok"], "no_path": counts["replan_no_path"],
            "replan_ms_p50": pct(replan_ms, 50), "replan_ms_p95": pct(replan_ms, 95),
            "collisions": counts["replan_collide"],
        },
        "metric_only": {
            "paths": counts["metric_ok"], "collisions": counts["metric_collide"],
            "collisions_with_objects": counts["metric_collide_objects"],
            "margin_violations": counts["metric_margin"],
            "collision_frac": counts["metric_collide"] / max(counts["metric_ok"], 1),
        },
        "altitudes": {f"{alt:.2f}m": t for alt, t in sorted(sweep.items())},
        "wall_time_s": wall_s,
    }
    print(f"planner benchmark: {args.rooms} rooms {args.size_m:g} x {args.size_m:g} m, {args.objects} objects, "
          f"altitude {z} m, radius {r} m, {cfg.algorithm}, budget {cfg.time_limit_s} s")
    print(" seed query      first   total  length  ratio source                   sem   replan  metric-only")
    for row in rows:
        print(row)
    s, rp, mo = figures["semantic"], figures["replan"], figures["metric_only"]
    print()
    print(f"semantic   paths {s['paths']}/{counts['queries']}  first path p50 {s['first_path_ms_p50']:.1f} ms "
          f"p95 {s['first_path_ms_p95']:.1f} ms (incl. map preparation p95 {s['first_path_incl_prepare_ms_p95']:.1f} ms)  "
          f"whole request p95 {s['planning_ms_p95']:.1f} ms")
    print(f"           length / reference p50 {s['length_ratio_p50']:.3f} p95 {s['length_ratio_p95']:.3f} "
          f"max {s['length_ratio_max']:.3f}, within 5 %: {s['length_within_5pct_frac'] * 100:.0f} %  "
          f"collisions {s['collisions']}  OMPL improved the first path in {s['ompl_improved_frac'] * 100:.0f} %")
    print(f"replan     {rp['paths']}/{rp['cases']} after a desk appears: p50 {rp['replan_ms_p50']:.1f} ms "
          f"p95 {rp['replan_ms_p95']:.1f} ms  collisions {rp['collisions']}")
    print(f"metric-only {mo['collisions']}/{mo['paths']} paths collide with the true geometry "
          f"({mo['collisions_with_objects']} with furniture), {mo['margin_violations']} pass closer than the "
          f"vertical margin")
    print()
    print("semantic vs metric-only map by altitude (first path + any-angle, no OMPL stage):")
    print("  altitude  queries | semantic: paths  hit  <margin | metric-only: paths  hit  <margin")
    for alt, t in sorted(sweep.items()):
        print(f"  {alt:6.2f} m  {t['queries']:7d} | {t['semantic_paths']:15d} {t['semantic_collisions']:4d} "
              f"{t['semantic_margin_violations']:8d} | {t['metric_paths']:18d} {t['metric_collisions']:4d} "
              f"{t['metric_margin_violations']:8d}")
    print(f"  (hit: the vehicle ({h} m tall, radius {r} m) touches the true geometry; <margin: it passes "
          f"closer than the vertical margin {cfg.vertical_margin_m} m above or below)")
    return figures


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 rooms of 12 x 12 m")
    ap.add_argument("--rooms", type=int, default=None)
    ap.add_argument("--size-m", type=float, default=None)
    ap.add_argument("--objects", type=int, default=None)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--time-limit-s", type=float, default=None, help="planner budget (default: config)")
    ap.add_argument("--altitude-m", type=float, default=None, help="flight altitude (default: config)")
    ap.add_argument("--altitudes", type=lambda v: [float(x) for x in v.split(",")],
                    default=[0.45, 0.6, 0.75], help="altitudes of the semantic vs metric comparison")
    ap.add_argument("--pictures", default=None, metavar="DIR",
                    help="save pictures of the first cases (semantic path blue, metric-only orange)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a PlannerConfig field (repeatable)")
    args = ap.parse_args(argv)
    if args.rooms is None:
        args.rooms = 4 if args.quick else 50
    if args.size_m is None:
        args.size_m = 12.0 if args.quick else 20.0
    if args.objects is None:
        args.objects = 14 if args.quick else 30
    figures = run(args)
    print(json.dumps(figures, sort_keys=True, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
