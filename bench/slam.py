"""2D SLAM on simulated flights with a drifting autopilot: trajectory error, loops, map, speed.

Each seeded room is flown twice around its perimeter (a loop, revisited) with a camera yaw
sweep; the mock autopilot's odometry drifts (3 % scale error, 0.5 deg/s heading drift, random
walk noise: :class:`companion.sim.odometry.OdometryDriftModel`). Every frame is rendered,
its altitude-band scan extracted in the gravity-aligned body frame and fed to
:class:`semmap.slam.Slam2D` with the drifting odometry as the prior.

Figures per room and overall:

* ATE RMSE (absolute trajectory error, metres, no alignment: both start at the true pose) of
  the drifting odometry, of SLAM's live poses (what mapping and the autopilot get at the
  time; also their error's p95 and maximum) and of SLAM's final re-anchored trajectory;
* loop closures found, odometry fallbacks;
* map agreement with ground truth as the semantic map issue measures it (``bench/_grid.py``):
  the semantic map's occupancy grid (its band, tables and scan extraction) built from every
  third frame, fraction of observed cells whose occupancy equals ``occupancy_at_band``. Built
  at the final (re-anchored) SLAM poses, at the live SLAM poses (what a map that is never
  re-anchored holds), at the drifting odometry's poses, and at the true poses (the ceiling:
  what depth noise and the grid itself allow);
* local SLAM time per scan (the live path), p50 / p95, milliseconds: wall time and the live
  thread's CPU time (the latter is what a scan costs on an otherwise idle core).

``python bench/slam.py [--quick]``; the last line is a JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.sim import groundtruth as gt  # noqa: E402
from companion.sim.odometry import OdometryDriftModel  # noqa: E402
from companion.sim.render import RoomRenderer  # noqa: E402
from companion.sim.trajectory import fly_route, plan_route  # noqa: E402
from companion.sim.world import LAYOUTS, generate_room  # noqa: E402
from semmap.config import ExtrinsicsConfig, SlamConfig, default_classes  # noqa: E402
from semmap.costmap import VerticalBand  # noqa: E402
from semmap.frames import wrap_angle_rad  # noqa: E402
from semmap.scan import BandScan, extract_band_scan  # noqa: E402
from semmap.semantic_map import SemanticMap, SemanticMapSettings  # noqa: E402
from semmap.slam import Slam2D, SlamStatus, level_scan_from_depth  # noqa: E402
from semmap.slam.pose2d import interpolate, transform_scan  # noqa: E402
from semmap.slam.scan2d import T_level_camera  # noqa: E402
from semmap.types import CameraIntrinsics  # noqa: E402

ALTITUDE_M = 0.6
#: The SLAM's scan band.
BAND = VerticalBand.for_altitude(ALTITUDE_M, 0.3, 0.1)
#: The semantic map's band and settings, as bench/_grid.py measures the occupancy grid.
MAP_BAND = VerticalBand.for_altitude(ALTITUDE_M, 0.15, 0.10)
#: Every this many frames goes into the agreement maps.
MAP_EVERY = 3


def loop_trajectory(room: Any, laps: int, speed_m_s: float, inset_m: float = 1.0) -> Any:
    """``laps`` counter-clockwise laps inset from the walls, sweeping the camera +-40 deg."""
    w, d = room.width_m, room.depth_m
    corners = [(inset_m, inset_m), (w - inset_m, inset_m), (w - inset_m, d - inset_m), (inset_m, d - inset_m)]
    wps = corners * laps + [corners[0]]
    route = plan_route(room, wps, ALTITUDE_M, 0.4, largest_component_only=True)
    return fly_route(route, ALTITUDE_M, speed_m_s, yaw_rate_max_rad_s=math.radians(90.0),
                     yaw_sweep_rad=math.radians(40.0), sweep_period_s=6.0)


def ate_rmse(est_xy: np.ndarray, true_xy: np.ndarray) -> float:
    """RMS of the position errors (metres) of (N, 2) estimates against (N, 2) truth."""
    return float(np.sqrt(np.mean(np.sum((est_xy - true_xy) ** 2, axis=1))))


def map_settings(room: Any, offset_xy_m: tuple[float, float]) -> SemanticMapSettings:
    """The semantic map's settings over the room (origin shifted by a fraction of a cell so
    walls do not sit on cell boundaries)."""
    classes = default_classes()
    return SemanticMapSettings(
        tuple(c.name for c in classes), MAP_BAND,
        origin_xy_m=(-1.0 + offset_xy_m[0], -1.0 + offset_xy_m[1]),
        size_xy_m=(room.width_m + 2.0, room.depth_m + 2.0),
        class_margins_m=tuple((c.name, c.margin_m) for c in classes),
    )


def map_agreement(room: Any, settings: SemanticMapSettings, scans: list[BandScan], poses: np.ndarray) -> float:
    """Agreement with ground truth of the semantic map's occupancy grid built from the level
    ``scans`` at (N, 3) ``poses``: observed cells whose occupancy (p > 0.5) equals
    ``occupancy_at_band``."""
    smap = SemanticMap(settings)
    for sc, p in zip(scans, poses, strict=True):
        smap.layers.update_scan(transform_scan(p, sc))
    truth = gt.occupancy_at_band(room, smap.spec, MAP_BAND)
    known = smap.grid.known
    occ = smap.grid.probability() > 0.5
    return float(((occ == truth) & known).sum() / max(1, int(known.sum())))


def pose_at(traj: np.ndarray, stamp_s: float) -> np.ndarray:
    """(3,) pose of an (M, 4) stamp, x, y, yaw trajectory at ``stamp_s`` (interpolated)."""
    k = int(np.searchsorted(traj[:, 0], stamp_s))
    if k <= 0:
        return traj[0, 1:].copy()
    if k >= len(traj):
        return traj[-1, 1:].copy()
    t0, t1 = traj[k - 1, 0], traj[k, 0]
    return interpolate(traj[k - 1, 1:], traj[k, 1:], 0.0 if t1 <= t0 else (stamp_s - t0) / (t1 - t0))


def run_flight(seed: int, laps: int = 2, speed_m_s: float = 0.3, rate_hz: float = 10.0,
               width_px: int = 320, cfg: SlamConfig | None = None,
               drift: OdometryDriftModel | None = None, max_duration_s: float | None = None,
               max_range_m: float = 6.0, layout: str = "realistic") -> dict[str, Any]:
    """Fly one seeded room (``layout``) with SLAM; returns its figures (see the module docstring)."""
    room = generate_room(seed, n_objects=8, layout=layout)
    traj = loop_trajectory(room, laps, speed_m_s)
    scale = width_px / 640.0
    intr = CameraIntrinsics(383.0 * scale, 383.0 * scale, 320.0 * scale, 240.0 * scale, width_px, int(480 * scale))
    renderer = RoomRenderer(room, [c.name for c in default_classes()], intr, seed=seed)
    T_body_camera = ExtrinsicsConfig().T_body_camera()
    drift = drift or OdometryDriftModel(0.03, 0.5, seed=seed)
    duration = traj.duration_s if max_duration_s is None else min(traj.duration_s, max_duration_s)
    n = int(duration * rate_hz)
    truth, odom, live, times, cpu_times, times_s = [], [], [], [], [], []
    map_scans: list[BandScan] = []
    map_index: list[int] = []
    settings = map_settings(room, tuple(np.random.default_rng(seed).uniform(0.1, 0.9, 2) * 0.05))
    n_fallback = n_partial = 0
    with Slam2D(cfg or SlamConfig()) as slam:
        for i in range(n):
            t = traj.start_s + i / rate_hz
            xyz, yaw = traj.state_at(t)
            T = traj.T_map_body(t) @ T_body_camera
            frame = renderer.render(T, stamp_s=t, index=i)
            scan = level_scan_from_depth(frame.depth_m, intr, T_body_camera, 0.0, 0.0, float(xyz[2]), BAND,
                                         max_depth_m=max_range_m,
                                         stride_px=2 if width_px > 200 else 1, stamp_s=t)
            o = drift.update(t, (xyz[0], xyz[1], yaw))
            t0, c0 = time.perf_counter(), time.thread_time()
            est = slam.add_scan(t, scan, o)
            times.append((time.perf_counter() - t0) * 1e3)
            # CPU time of the live thread alone: what a scan costs whatever else (the loop
            # closer, other processes) shares the CPU.
            cpu_times.append((time.thread_time() - c0) * 1e3)
            n_fallback += est.status is SlamStatus.DEGENERATE_FALLBACK_ODOMETRY
            n_partial += est.status is SlamStatus.PARTIAL_ODOMETRY
            truth.append((xyz[0], xyz[1], yaw))
            odom.append(o)
            live.append(est.pose_map)
            times_s.append(t)
            if i % MAP_EVERY == 0:
                ms = settings
                map_scans.append(extract_band_scan(
                    frame.depth_m, intr, T_level_camera(T_body_camera, 0.0, 0.0, float(xyz[2])), ms.scan_band,
                    ms.depth_min_m, ms.depth_max_m, ms.scan_stride_px, ms.scan_min_hit_points, stamp_s=t,
                    column_stride_px=ms.scan_column_stride_px))
                map_index.append(i)
        slam.drain(timeout_s=300.0)
        slam.optimize()
        final = slam.trajectory()
        loops = slam.loop_closures
        # Closures against submaps built long before (not the neighbours of the node's own):
        # the revisits of the loop.
        nodes = slam.global_.nodes
        revisits = sum(1 for c in slam.global_.loop_closures
                       if nodes[c.node].submaps and c.submap < min(nodes[c.node].submaps) - 2)
    truth_a, odom_a, live_a = np.array(truth), np.array(odom), np.array(live)
    idx = np.array(map_index)
    final_at = np.array([pose_at(final, times_s[k]) for k in idx])
    agree = {name: map_agreement(room, settings, map_scans, poses) for name, poses in (
        ("slam", final_at), ("slam_live", live_a[idx]), ("odometry", odom_a[idx]), ("true_poses", truth_a[idx]))}
    return {
        "seed": seed, "duration_s": duration, "scans": n,
        "ate_odometry_m": ate_rmse(odom_a[:, :2], truth_a[:, :2]),
        "ate_slam_live_m": ate_rmse(live_a[:, :2], truth_a[:, :2]),
        "live_err_p95_m": float(np.percentile(np.linalg.norm(live_a[:, :2] - truth_a[:, :2], axis=1), 95)),
        "live_err_max_m": float(np.max(np.linalg.norm(live_a[:, :2] - truth_a[:, :2], axis=1))),
        "ate_slam_m": ate_rmse(final[:, 1:3], truth_a[:, :2]),
        "yaw_err_slam_deg_rms": float(np.degrees(np.sqrt(np.mean(
            wrap_angle_rad(final[:, 3] - truth_a[:, 2]) ** 2)))),
        "loop_closures": loops, "revisit_closures": revisits, "fallbacks": n_fallback, "partial_odometry": n_partial,
        **{f"agreement_{k}": v for k, v in agree.items()},
        "local_ms": times, "local_cpu_ms": cpu_times,
    }


def _fly_all(args: argparse.Namespace, seeds: list[int], layout: str) -> dict[str, Any]:
    """Fly every seed's room laid out ``layout``, print the table, return the summary figures."""
    results = []
    for seed in seeds:
        if args.quick:
            r = run_flight(seed, laps=1, speed_m_s=0.6, rate_hz=6.0, width_px=160, layout=layout)
        else:
            r = run_flight(seed, layout=layout)
        results.append(r)
    print(f"{'seed':>4} {'dur s':>6} {'scans':>5} {'ATE odom m':>10} {'ATE live m':>10} {'live p95':>8} {'ATE SLAM m':>10} "
          f"{'loops':>5} {'revis':>5} {'fallb':>5} {'part':>5} {'agree slam':>10} {'live':>6} {'odom':>6} {'truth':>6} "
          f"{'local p50 ms':>12}")
    for r in results:
        print(f"{r['seed']:>4} {r['duration_s']:6.1f} {r['scans']:5d} {r['ate_odometry_m']:10.3f} "
              f"{r['ate_slam_live_m']:10.3f} {r['live_err_p95_m']:8.3f} {r['ate_slam_m']:10.3f} {r['loop_closures']:5d} {r['revisit_closures']:5d} {r['fallbacks']:5d} "
              f"{r['partial_odometry']:5d} {r['agreement_slam']:10.3f} {r['agreement_slam_live']:6.3f} "
              f"{r['agreement_odometry']:6.3f} {r['agreement_true_poses']:6.3f} {np.percentile(r['local_ms'], 50):12.2f}")
    all_ms = np.concatenate([r["local_ms"] for r in results])
    all_cpu = np.concatenate([r["local_cpu_ms"] for r in results])
    return {
        "rooms": {str(r["seed"]): {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()
                                   if k not in ("local_ms", "local_cpu_ms")} for r in results},
        "ate_odometry_m_mean": round(float(np.mean([r["ate_odometry_m"] for r in results])), 4),
        "ate_slam_m_mean": round(float(np.mean([r["ate_slam_m"] for r in results])), 4),
        "ate_slam_m_max": round(float(np.max([r["ate_slam_m"] for r in results])), 4),
        "ate_slam_live_m_mean": round(float(np.mean([r["ate_slam_live_m"] for r in results])), 4),
        "ate_slam_live_m_max": round(float(np.max([r["ate_slam_live_m"] for r in results])), 4),
        "live_err_p95_m_max": round(float(np.max([r["live_err_p95_m"] for r in results])), 4),
        "loop_closures_min": int(min(r["loop_closures"] for r in results)),
        "revisit_closures_min": int(min(r["revisit_closures"] for r in results)),
        "agreement_slam_mean": round(float(np.mean([r["agreement_slam"] for r in results])), 4),
        "agreement_slam_min": round(float(np.min([r["agreement_slam"] for r in results])), 4),
        "agreement_slam_live_mean": round(float(np.mean([r["agreement_slam_live"] for r in results])), 4),
        "agreement_odometry_mean": round(float(np.mean([r["agreement_odometry"] for r in results])), 4),
        "agreement_true_poses_mean": round(float(np.mean([r["agreement_true_poses"] for r in results])), 4),
        "fallbacks_total": int(sum(r["fallbacks"] for r in results)),
        "partial_odometry_total": int(sum(r["partial_odometry"] for r in results)),
        "local_slam_ms_p50": round(float(np.percentile(all_ms, 50)), 3),
        "local_slam_ms_p95": round(float(np.percentile(all_ms, 95)), 3),
        "local_slam_cpu_ms_p50": round(float(np.percentile(all_cpu, 50)), 3),
        "local_slam_cpu_ms_p95": round(float(np.percentile(all_cpu, 95)), 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one room, one short loop, small images (< 1 min)")
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("--world", choices=LAYOUTS, default="realistic", help="room layout")
    ap.add_argument("--no-scattered", action="store_true",
                    help="with --world realistic: skip flying the same seeds scattered")
    args = ap.parse_args(argv)
    seeds = args.seeds or ([3] if args.quick else [1, 2, 3])
    summary = {"world": args.world, **_fly_all(args, seeds, args.world)}
    if args.world == "realistic" and not args.no_scattered:
        print("\n-- the same seeds, scattered layout")
        scattered = _fly_all(args, seeds, "scattered")
        summary["scattered"] = {k: v for k, v in scattered.items() if k != "rooms"}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
