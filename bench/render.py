"""Speed of the simulated RGB-D camera (:mod:`companion.sim.render`) at 640x480.

Run ``python bench/render.py`` (200 frames per case) or ``--quick`` (30 frames). Poses follow a
doorway-to-doorway flight with a yaw sweep through the default config's seeded room, so the
views are the ones the demo and the pipeline see. Cases:

* ``raycast``: the Open3D ray cast alone (one ray per pixel, hit depth + primitive ids);
* ``frame``: a whole frame: ray cast, shading and textures, D455 depth noise with edge
  dropout, instance and class masks;
* ``visible_objects``: the ground-truth list of objects in a rendered frame.

Target: 30 Hz for ``frame`` (33 ms) on the drone's class of CPU. Figures on a loaded shared
machine are pessimistic. The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.config import CompanionConfig  # noqa: E402
from companion.sim.demo import build_world  # noqa: E402


def _stats_ms(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 2),
        "p95_ms": round(float(np.percentile(ms, 95)), 2),
        "mean_ms": round(float(ms.mean()), 2),
        "fps": round(float(1e3 / ms.mean()), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="30 frames per case instead of 200")
    ap.add_argument("--frames", type=int, default=None, help="frames per case (overrides --quick)")
    ap.add_argument("--threads", type=int, default=0, help="ray-cast threads (0: all cores)")
    args = ap.parse_args()
    n = args.frames or (30 if args.quick else 200)

    cfg = CompanionConfig()
    t0 = time.perf_counter()
    world = build_world(cfg)
    renderer = world.renderer
    renderer.n_threads = args.threads
    setup_s = time.perf_counter() - t0
    T_bc = cfg.camera.extrinsics.T_body_camera()
    traj = world.trajectory
    stamps = traj.start_s + np.linspace(0.0, traj.duration_s, n)
    poses = [traj.T_map_body(t) @ T_bc for t in stamps]
    intr = renderer.intrinsics

    renderer.render(poses[0])  # warm-up: first-call allocations and Embree's BVH
    cast_s, frame_s, vis_s = [], [], []
    for T in poses:
        a = time.perf_counter()
        renderer.cast(T)
        cast_s.append(time.perf_counter() - a)
    frames = []
    for i, T in enumerate(poses):
        a = time.perf_counter()
        f = renderer.render(T, stamp_s=float(stamps[i]), index=i)
        frame_s.append(time.perf_counter() - a)
        frames.append(f)
    for f in frames:
        a = time.perf_counter()
        renderer.visible_objects(f)
        vis_s.append(time.perf_counter() - a)

    cases = {"raycast": _stats_ms(cast_s), "frame": _stats_ms(frame_s), "visible_objects": _stats_ms(vis_s)}
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"== Simulated RGB-D camera, {intr.width_px}x{intr.height_px}, {n} frames per case ==")
    print(f"room seed {world.room.seed}: {renderer.n_primitives} primitives, scene setup {setup_s:.2f} s; "
          f"{os.cpu_count()} CPUs, load average {load:.2f}, {platform.processor() or platform.machine()}")
    print(f"{'case':<18}{'p50 ms':>9}{'p95 ms':>9}{'mean ms':>9}{'fps':>8}")
    for name, s in cases.items():
        print(f"{name:<18}{s['p50_ms']:>9.2f}{s['p95_ms']:>9.2f}{s['mean_ms']:>9.2f}{s['fps']:>8.1f}")
    meets = cases["frame"]["p50_ms"] <= 1e3 / 30.0
    print(f"full frame at 30 Hz (33.3 ms): {'met' if meets else 'NOT met'} at p50 on this machine")
    out = {
        "resolution": f"{intr.width_px}x{intr.height_px}",
        "frames_per_case": n,
        "primitives": renderer.n_primitives,
        "load_average_1min": round(load, 2),
        "cpus": os.cpu_count(),
        **cases,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
