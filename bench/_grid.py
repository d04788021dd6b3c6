"""Occupancy grid and semantic layers: accuracy against ground truth, per-frame time, memory.

Used by ``bench/mapping.py`` (section ``grid``) and runnable alone:
``python bench/_grid.py [--quick]``. Each seeded room is flown at the default flight altitude
(0.6 m) on a loop inset from the walls, the camera yawing towards the room centre and
sweeping +-60 degrees so walls behind furniture are seen too; every frame is rendered with
D455-like depth noise and integrated into a :class:`SemanticMap`, and the ground-truth object
footprints (jittered, existence rising, so every object layer redraws every frame) stand in
for the object map.

Figures:

* agreement: fraction of observed cells (grid value known) whose occupancy (p > 0.5) equals
  ``occupancy_at_band`` at the scan band, pooled over all rooms (target >= 0.95; the worst
  room is reported too). The grid origin is offset by a random fraction of a cell so walls
  do not sit on cell boundaries (the real world does not align);
* coverage of the room interior, false-occupied and false-free fractions;
* per-frame time of scan extraction, grid update and layer update (10 objects), p50/p99;
* memory of a 50 m x 50 m map at 5 cm with every layer materialised; target <= 150 MB.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.sim import groundtruth as gt  # noqa: E402
from companion.sim.render import DepthNoise, RoomRenderer  # noqa: E402
from companion.sim.world import Room, generate_room  # noqa: E402
from semmap.config import default_classes  # noqa: E402
from semmap.costmap import ObjectFootprint, VerticalBand  # noqa: E402
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, rotation_from_rpy  # noqa: E402
from semmap.scan import extract_band_scan  # noqa: E402
from semmap.semantic_map import SemanticMap, SemanticMapSettings  # noqa: E402
from semmap.types import CameraIntrinsics  # noqa: E402

INTRINSICS = CameraIntrinsics(383.0, 383.0, 320.0, 240.0, 640, 480)
ALTITUDE_M = 0.6
#: The default scan band: flight altitude +- (vehicle height / 2 + vertical margin).
BAND = VerticalBand.for_altitude(ALTITUDE_M, 0.15, 0.10)
CLASSES = default_classes()


def grid_flight(room: Room, n_frames: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera poses (4, 4) on a loop 0.7 m inside the walls, looking at the centre +- 60 deg,
    skipping positions where the vehicle's band would be within 0.25 m of furniture."""
    inset = 0.7
    x0, x1, y0, y1 = inset, room.width_m - inset, inset, room.depth_m - inset
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    centre = np.array([room.width_m / 2, room.depth_m / 2])
    poses: list[np.ndarray] = []
    phase = float(rng.uniform(0, 2 * math.pi))
    for k, s in enumerate(np.linspace(0.0, seg.sum(), n_frames, endpoint=False)):
        i = int(np.searchsorted(np.cumsum(seg), s, side="right"))
        t = (s - (np.cumsum(seg)[i - 1] if i else 0.0)) / seg[i]
        xy = corners[i] + t * (corners[i + 1] - corners[i])
        # The vehicle never flies where its band meets furniture (under a desk top, say).
        band_height = BAND.z_max_m - BAND.z_min_m
        if gt.clearance_m(room, np.array([[xy[0], xy[1], ALTITUDE_M]]), band_height)[0] < 0.25:
            continue
        look = centre - xy
        yaw = math.atan2(look[1], look[0]) + math.radians(60) * math.sin(phase + 0.35 * k)
        R = rotation_from_rpy(0.0, 0.0, yaw) @ R_BODY_CAMERA_FORWARD
        poses.append(make_transform(R, np.array([xy[0], xy[1], ALTITUDE_M])))
    return poses


def jittered(fps: list[ObjectFootprint], rng: np.random.Generator, existence: float) -> list[ObjectFootprint]:
    """Ground-truth footprints moved by ~1 cm with a new existence (forces a redraw)."""
    return [
        ObjectFootprint(f.object_id, f.class_name, f.polygon_xy_m + rng.normal(0.0, 0.01, 2), f.z_min_m,
                        f.z_max_m, existence=existence, margin_m=f.margin_m)
        for f in fps
    ]


def map_room(seed: int, n_frames: int, layout: str = "realistic") -> dict[str, Any]:
    """Fly one room; returns its agreement figures and per-frame stage times (ms)."""
    rng = np.random.default_rng(seed)
    room = generate_room(seed, width_m=float(rng.uniform(6.0, 8.0)), depth_m=float(rng.uniform(5.0, 6.5)),
                         n_objects=10, layout=layout)
    renderer = RoomRenderer(room, [c.name for c in CLASSES], INTRINSICS, noise=DepthNoise(), seed=seed)
    off = rng.uniform(0.1, 0.9, 2) * 0.05
    settings = SemanticMapSettings(
        tuple(c.name for c in CLASSES), BAND, origin_xy_m=(-1.0 + off[0], -1.0 + off[1]),
        size_xy_m=(room.width_m + 2.0, room.depth_m + 2.0),
        class_margins_m=tuple((c.name, c.margin_m) for c in CLASSES),
    )
    smap = SemanticMap(settings)
    truth_fps = gt.object_footprints(room, {c.name: c.margin_m for c in CLASSES})
    times: dict[str, list[float]] = {"scan": [], "grid": [], "layers": [], "cpu": []}
    s = smap.settings
    for i, T in enumerate(grid_flight(room, n_frames, rng)):
        frame = renderer.render(T, stamp_s=i / 15.0, index=i)
        objs = jittered(truth_fps, rng, existence=min(0.99, 0.3 + 0.05 * i))
        c0 = time.process_time()
        t0 = time.perf_counter()
        scan = extract_band_scan(frame.depth_m, INTRINSICS, T, s.scan_band, s.depth_min_m, s.depth_max_m,
                                 s.scan_stride_px, s.scan_min_hit_points, stamp_s=frame.stamp_s,
                                 column_stride_px=s.scan_column_stride_px)
        t1 = time.perf_counter()
        smap.layers.update_scan(scan)
        t2 = time.perf_counter()
        smap.set_objects(objs, frame.stamp_s)
        t3 = time.perf_counter()
        # Process CPU time of the three stages: what they cost on an idle machine, whatever
        # else shares the CPU while the benchmark runs.
        c3 = time.process_time()
        for key, dt in (("scan", t1 - t0), ("grid", t2 - t1), ("layers", t3 - t2), ("cpu", c3 - c0)):
            times[key].append(dt * 1e3)
    spec = smap.spec
    truth = gt.occupancy_at_band(room, spec, BAND)
    known = smap.grid.known
    occ = smap.grid.probability() > 0.5
    n_known = int(known.sum())
    inside = gt.interior_mask(room, spec)
    return {
        "n_known": n_known,
        "n_agree": int(((occ == truth) & known).sum()),
        "agreement": float(((occ == truth) & known).sum() / max(1, n_known)),
        "coverage": float((known & inside).sum() / max(1, inside.sum())),
        "false_occupied": float((known & occ & ~truth).sum() / max(1, n_known)),
        "false_free": float((known & ~occ & truth).sum() / max(1, n_known)),
        "times_ms": times,
        "frames": len(times["scan"]),
    }


def memory_figures(n_objects: int = 10) -> dict[str, float]:
    """Bytes of a 50 m x 50 m map at 5 cm with every layer materialised (tracemalloc peak
    while building it and answering a costmap, class planes and heights)."""
    tracemalloc.start()
    settings = SemanticMapSettings(
        tuple(c.name for c in CLASSES), BAND, origin_xy_m=(-25.0, -25.0), size_xy_m=(50.0, 50.0),
        fixed_size=True, class_margins_m=tuple((c.name, c.margin_m) for c in CLASSES),
    )
    smap = SemanticMap(settings)
    rng = np.random.default_rng(0)
    smap.grid.values[:] = rng.integers(0, 32768, smap.spec.shape_rc, dtype=np.uint16)
    square = np.array([[0.0, 0.0], [1.2, 0.0], [1.2, 0.8], [0.0, 0.8]])
    objs = [
        ObjectFootprint(i + 1, CLASSES[i % len(CLASSES)].name, square + rng.uniform(-20, 20, 2), 0.0, 0.8, 0.9)
        for i in range(n_objects)
    ]
    smap.set_objects(objs, 1.0)
    cm = smap.costmap()
    planes = smap.layers.classes.probabilities(smap.spec)
    heights = smap.layers.heights.heights_m(smap.spec)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    held = smap.nbytes() + cm.cost.nbytes + (cm.class_index.nbytes if cm.class_index is not None else 0)
    held += planes.nbytes + heights.nbytes
    return {
        "cells": float(smap.spec.rows * smap.spec.cols),
        "held_mb": round(held / 1e6, 2),
        "peak_mb": round(peak / 1e6, 2),
    }


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def grid_section(args: argparse.Namespace) -> tuple[list[str], dict[str, Any]]:
    """The ``grid`` section of bench/mapping.py: (table lines, figures)."""
    n_rooms = 3 if args.quick else min(args.rooms, 10)
    n_frames = 50 if args.quick else max(80, args.frames)
    rooms = [map_room(args.seed + 500 + k, n_frames, args.world) for k in range(n_rooms)]
    lines = [f"  {'room':<6}{'frames':>7}{'agree':>9}{'cover':>9}{'f_occ':>9}{'f_free':>9}"]
    for k, r in enumerate(rooms):
        lines.append(f"  {k:<6}{r['frames']:>7}{r['agreement']:>9.3f}{r['coverage']:>9.3f}"
                     f"{r['false_occupied']:>9.3f}{r['false_free']:>9.3f}")
    times = {key: [t for r in rooms for t in r["times_ms"][key]] for key in ("scan", "grid", "layers")}
    total = [a + b + c for a, b, c in zip(times["scan"], times["grid"], times["layers"], strict=True)]
    cpu = [t for r in rooms for t in r["times_ms"]["cpu"]]
    mem = memory_figures()
    agreements = [r["agreement"] for r in rooms]
    figures: dict[str, Any] = {
        "rooms": n_rooms,
        # Pooled over every observed cell of every room: "agrees on >= 95 % of observed cells".
        "agreement_pooled": round(sum(r["n_agree"] for r in rooms) / max(1, sum(r["n_known"] for r in rooms)), 4),
        "agreement_mean": round(float(np.mean(agreements)), 4),
        "agreement_min": round(float(np.min(agreements)), 4),
        "coverage_mean": round(float(np.mean([r["coverage"] for r in rooms])), 4),
        "false_occupied_mean": round(float(np.mean([r["false_occupied"] for r in rooms])), 4),
        "false_free_mean": round(float(np.mean([r["false_free"] for r in rooms])), 4),
    }
    for key, vals in {**times, "scan_grid_layers": total, "scan_grid_layers_cpu": cpu}.items():
        figures[f"{key}_ms_p50"] = round(_pct(vals, 50), 3)
        figures[f"{key}_ms_p99"] = round(_pct(vals, 99), 3)
    figures["memory_50m_5cm_held_mb"] = mem["held_mb"]
    figures["memory_50m_5cm_peak_mb"] = mem["peak_mb"]
    lines.append("")
    lines.append(f"  {'stage (640x480, 10 objects)':<30}{'p50 ms':>9}{'p99 ms':>9}")
    for key in ("scan", "grid", "layers", "scan_grid_layers", "scan_grid_layers_cpu"):
        lines.append(f"  {key:<30}{figures[key + '_ms_p50']:>9.3f}{figures[key + '_ms_p99']:>9.3f}")
    lines.append(f"  memory, 50 m x 50 m at 5 cm, all layers: held {mem['held_mb']:.1f} MB, "
                 f"peak {mem['peak_mb']:.1f} MB")
    targets = {
        "agreement_pooled": (figures["agreement_pooled"] >= 0.95, ">= 0.95"),
        "memory_50m_5cm_peak_mb": (mem["peak_mb"] <= 150.0, "<= 150"),
    }
    lines.append("")
    for key, (ok, target) in targets.items():
        lines.append(f"  {key:<28} {figures[key]:>8.3f}  target {target:<7} {'PASS' if ok else 'FAIL'}")
    figures["targets_met"] = all(ok for ok, _ in targets.values())
    return lines, figures


def bench_map_update(quick: bool) -> dict[str, object]:
    """Per-frame scan extraction + grid update + layer update (10 objects) at 640x480, for
    ``bench/perception.py``: frames are rendered first, only the map update is timed."""
    seed = 77
    rng = np.random.default_rng(seed)
    room = generate_room(seed, width_m=7.0, depth_m=6.0, n_objects=10)
    renderer = RoomRenderer(room, [c.name for c in CLASSES], INTRINSICS, noise=DepthNoise(), seed=seed)
    frames = [renderer.render(T, stamp_s=i / 15.0, index=i)
              for i, T in enumerate(grid_flight(room, 30 if quick else 120, rng))]
    settings = SemanticMapSettings(
        tuple(c.name for c in CLASSES), BAND, origin_xy_m=(-1.0, -1.0), size_xy_m=(9.0, 8.0),
        class_margins_m=tuple((c.name, c.margin_m) for c in CLASSES),
    )
    smap = SemanticMap(settings)
    truth_fps = gt.object_footprints(room, {c.name: c.margin_m for c in CLASSES})
    samples: list[float] = []
    cpu: list[float] = []
    for rep in range(2 if quick else 3):
        for i, frame in enumerate(frames):
            objs = jittered(truth_fps, rng, existence=min(0.99, 0.3 + 0.02 * (i + rep)))
            c0, t0 = time.process_time(), time.perf_counter()
            smap.integrate_frame(frame, objects=objs)
            samples.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
    out = {"frames": len(samples), "objects": len(truth_fps),
           "ms_p50": round(_pct(samples, 50), 3), "ms_p99": round(_pct(samples, 99), 3),
           "cpu_ms_p50": round(_pct(cpu, 50), 3), "cpu_ms_p99": round(_pct(cpu, 99), 3)}
    print("\n== map update: band scan + grid + layers (no object geometry) ==")
    print(f"  scan + grid + layers (640x480, {len(truth_fps)} objects): p50 {out['ms_p50']:.3f} ms, "
          f"p99 {out['ms_p99']:.3f} ms wall; CPU p50 {out['cpu_ms_p50']:.3f} ms, "
          f"p99 {out['cpu_ms_p99']:.3f} ms; {len(samples)} frames")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 short rooms (under a minute)")
    ap.add_argument("--rooms", type=int, default=10)
    ap.add_argument("--frames", type=int, default=120, help="frames per room")
    ap.add_argument("--seed", type=int, default=1000)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    lines, figures = grid_section(args)
    print(f"== grid ({time.perf_counter() - t0:.0f} s)")
    for line in lines:
        print(line)
    print(json.dumps({"grid": figures}))
    return 0


__all__ = ["bench_map_update", "grid_section", "map_room", "memory_figures"]

if __name__ == "__main__":
    raise SystemExit(main())
