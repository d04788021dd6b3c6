"""Indoors without GPS: PX4 SITL flies on the companion's SLAM pose, judged against SIH's truth.

``python bench/px4_gps_denied.py [--rooms N] [--quick] [--no-slam-loss]``

Each room: a fresh PX4 SITL with GPS off and EKF2 fed only by external vision
(:data:`companion.sim.px4_gps_denied.GPS_DENIED_PX4_PARAMS`), the camera rendered from SIH's
true pose (HIL_STATE_QUATERNION on its display link, never PX4's estimate), and the whole
service flying the demo crossing with SLAM localization and its pose sent as ODOMETRY
(:func:`companion.sim.px4_gps_denied_flight.fly_gps_denied`). Figures per room:

* ``waypoints_reached``/``waypoints_total``, ``collisions`` (the true path against the room);
* ``ekf_vs_truth_error_m_p95``: PX4's LOCAL_POSITION_NED against SIH's truth at its arrival
  (loopback; PX4's HIL_STATE_QUATERNION carries no time, so the truth is stamped on arrival
  too), horizontal, airborne, after aligning the frames on the ground (where each started),
  without the injected SLAM loss and the 3 s after it (``..._with_slam_loss`` keeps them);
* ``slam_vs_truth_error_m_p95``: the SLAM pose against the truth at its capture time;
* ``ev_rate_hz_at_px4``: PX4's ``uorb top`` rate of ``vehicle_visual_odometry`` in OFFBOARD
  (the stream repeats a pose between scans; ``ev_new_pose_rate_hz`` counts new ones).

Then the first room is flown once more and loses the SLAM for 3 s once its first leg is flown
(the camera stops; ``loss-<seed>/``): the vehicle must hold on PX4's estimate, touch nothing,
and resume or land by itself. Whether it resumes depends on PX4's landing deadline from its
height (:mod:`companion.service.vision_loss`), so that flight's waypoints are not the
mission's. Targets: every waypoint, 0 collisions (the loss flight's included), EKF within
0.15 m p95 of the truth, external vision >= 20 Hz at PX4.

By default the SLAM's motion prior is what the service makes of frames without odometry,
dead-reckoned from PX4's velocity, which without GPS is built from the SLAM's own pose;
``--odometry-sensor`` gives the vehicle an odometry of its own (the truth through the mock's
odometry drift, as a flow sensor or VIO would deliver it) and ``--weak-prior`` loosens the
SLAM's pull towards its prior instead. ``--flow-sensor`` wires a downward optical-flow sensor
to PX4 (made from SIH's truth, :mod:`companion.sim.flow_sensor`), which gives EKF2 a velocity
of its own while the SLAM is lost: without one PX4 holds on its IMU alone.

PX4 SITL and the whole service load both cores of this machine: the load average is printed
with the figures; ``--detector oracle --camera-scale 0.5`` leaves the SLAM more of them.
``--quick`` flies one room without the SLAM loss (25-45 s). The last line is one JSON object.
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
from companion.sim.flow_sensor import FLOW_PX4_PARAMS, FlowSensorModel  # noqa: E402
from companion.sim.odometry import OdometryDriftModel  # noqa: E402
from companion.sim.px4_gps_denied import GPS_DENIED_PX4_PARAMS, GpsDeniedSitl  # noqa: E402
from companion.sim.px4_gps_denied_flight import fly_gps_denied  # noqa: E402
from companion.sim.px4_sitl import Px4SitlError  # noqa: E402

EKF_TARGET_M = 0.15
EV_TARGET_HZ = 20.0
SLAM_LOSS_S = 3.0
#: SLAM settings for a motion prior that is no independent measurement (``--weak-prior``).
WEAK_PRIOR = {"correlative_linear_window_m": 0.3, "correlative_angular_window_deg": 10.0,
              "translation_weight": 1.0, "rotation_weight": 1.0, "odometry_calibration_window_s": 0.0}
log = logging.getLogger("bench.px4_gps_denied")


async def fly_room(cfg: Any, seed: int, out: Path, timeout_s: float, slam_loss_s: float,
                   odometry_sensor: bool, flow_sensor: bool) -> dict[str, Any] | None:
    """One flight in room ``seed`` (outputs in ``room-<seed>``, or ``loss-<seed>`` with a SLAM loss)."""
    c = with_seed(cfg, seed)
    try:
        sitl = await asyncio.to_thread(start_sitl, c, log, GpsDeniedSitl,
                                       params=FLOW_PX4_PARAMS if flow_sensor else None)
    except Px4SitlError as exc:
        log.error("room %d not flown: %s", seed, exc)
        return None
    with sitl:
        t0 = time.monotonic()
        odometry = OdometryDriftModel(seed=seed) if odometry_sensor else None
        name = f"loss-{seed}" if slam_loss_s > 0.0 else f"room-{seed}"
        summary = await fly_gps_denied(c, out / name, sitl, timeout_s=timeout_s, slam_loss_s=slam_loss_s,
                                       odometry=odometry, flow=FlowSensorModel(seed=seed) if flow_sensor else None)
        log.info("room %d flown in %.0f s", seed, time.monotonic() - t0)
    return summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap, rooms=3, quick_help="1 room, no SLAM loss flight")
    ap.add_argument("--no-slam-loss", action="store_true", help="no flight with the camera stopped mid-flight")
    ap.add_argument("--slam-loss-s", type=float, default=SLAM_LOSS_S,
                    help=f"how long the camera stops (default {SLAM_LOSS_S:g} s; longer than "
                         "link.vision_lost_hold_s plus the landing deadline: the vehicle lands)")
    ap.add_argument("--altitude", type=float, default=None,
                    help="flight altitude above the floor (m; default planner.flight_altitude_m)")
    ap.add_argument("--vision-std-m", type=float, default=None,
                    help="the SLAM pose's position 1-sigma sent to PX4 (m; default link.vision_position_std_m)")
    ap.add_argument("--camera-scale", type=float, default=1.0,
                    help="scale the camera's resolution and intrinsics (0.5: 320x240), for a loaded machine")
    ap.add_argument("--camera-rate-hz", type=float, default=None,
                    help="the camera's frame rate, and so the SLAM's (default camera.rate_hz; a D455 streams 30)")
    ap.add_argument("--weak-prior", action="store_true",
                    help="the SLAM trusts its motion prior less (wider search, weaker pull): without GPS that prior, "
                         "dead-reckoned from PX4's velocity, is itself built on the vision PX4 fuses")
    ap.add_argument("--odometry-sensor", action="store_true",
                    help="the vehicle has an odometry sensor of its own (flow, VIO: the truth drifting as "
                         "the mock's odometry) for the SLAM's motion prior, instead of PX4's velocity")
    ap.add_argument("--flow-sensor", action="store_true",
                    help="a downward optical-flow sensor wired to PX4 (made from SIH's truth, sent as "
                         "OPTICAL_FLOW_RAD; EKF2 fuses it with the vision): PX4 keeps a velocity when the SLAM is lost")
    args = ap.parse_args()
    prepared = prepare(args, "px4_gps_denied", log)
    if prepared is None:
        return 2
    cfg, out = prepared
    n = 1 if args.quick else args.rooms
    if args.camera_scale != 1.0:
        c, k = cfg.camera, args.camera_scale
        cfg = cfg.model_copy(update={"camera": c.model_copy(update={
            "width_px": int(c.width_px * k), "height_px": int(c.height_px * k), "fx_px": c.fx_px * k,
            "fy_px": c.fy_px * k, "cx_px": c.cx_px * k, "cy_px": c.cy_px * k})})
    if args.camera_rate_hz is not None:
        cfg = cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"rate_hz": args.camera_rate_hz})})
    if args.weak_prior:
        cfg = cfg.model_copy(update={"slam": cfg.slam.model_copy(update=WEAK_PRIOR)})
    if args.vision_std_m is not None:
        cfg = cfg.model_copy(update={"link": cfg.link.model_copy(update={"vision_position_std_m": args.vision_std_m})})
    if args.altitude is not None:
        cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"flight_altitude_m": args.altitude})})
    camera = (f"{cfg.camera.width_px}x{cfg.camera.height_px} at {cfg.camera.rate_hz:g} Hz, detector "
              f"{cfg.detector.kind}, SLAM prior {'weak' if args.weak_prior else 'as shipped'} from "
              f"{'an odometry sensor' if args.odometry_sensor else 'PX4 velocity'}, vision 1-sigma "
              f"{cfg.link.vision_position_std_m:g} m{', a flow sensor on PX4' if args.flow_sensor else ''}")
    load0 = os.getloadavg()
    t0 = time.monotonic()
    seeds = room_seeds(cfg, args.seed, n)
    rooms: dict[str, dict[str, Any]] = {}
    for seed in seeds:
        summary = asyncio.run(fly_room(cfg, seed, out, args.timeout, 0.0, args.odometry_sensor, args.flow_sensor))
        if summary is not None:
            rooms[str(seed)] = summary
    losses: dict[str, dict[str, Any]] = {}
    if not (args.quick or args.no_slam_loss):
        summary = asyncio.run(fly_room(cfg, seeds[0], out, args.timeout, args.slam_loss_s, args.odometry_sensor,
                                         args.flow_sensor))
        if summary is not None:
            losses[str(seeds[0])] = summary
    load1 = os.getloadavg()
    return report(rooms, out, time.monotonic() - t0, load0, load1, camera, args.slam_loss_s, losses)


def report(rooms: dict[str, dict[str, Any]], out: Path, elapsed_s: float,
           load0: tuple[float, float, float], load1: tuple[float, float, float], camera: str,
           slam_loss_s: float = SLAM_LOSS_S, loss_flights: dict[str, dict[str, Any]] | None = None) -> int:
    """Print the table and the JSON line: the mission figures from ``rooms``, the SLAM loss
    scenario's from ``loss_flights`` (room seed -> summary)."""
    print(f"PX4 SITL without GPS, on the companion's SLAM pose: {len(rooms)} rooms, {elapsed_s:.0f} s, outputs in {out}")
    print(f"PX4 parameters: {GPS_DENIED_PX4_PARAMS}")
    print(f"camera: {camera}")
    print(f"machine: {os.cpu_count()} cores, load average (1 min) {load0[0]:.1f} at start, {load1[0]:.1f} at end "
          "(PX4 SITL and the whole service share them)")
    print(f"{'room':>6} {'waypoints':>9} {'coll':>4} {'clear_m':>7} {'ekf_p95':>7} {'ekf_z95':>7} {'slam_p95':>8} "
          f"{'ev_Hz':>6} {'new_Hz':>6}  vision loss")
    cases: dict[str, Any] = {}
    loss_flights = loss_flights or {}
    flights = list(rooms.items()) + [(f"loss-{seed}", s) for seed, s in loss_flights.items()]
    for seed, s in flights:
        def f(v: Any) -> str:
            return "-" if v is None else f"{v}"
        print(f"{seed:>6} {s['waypoints_reached']:>4}/{s['waypoints_total']:<4} {s['collisions']:>4} "
              f"{f(s['min_clearance_m']):>7} {f(s['ekf_vs_truth_error_m_p95']):>7} "
              f"{f(s.get('ekf_vs_truth_height_error_m_p95')):>7} {f(s['slam_vs_truth_error_m_p95']):>8} "
              f"{f(s['ev_rate_hz_at_px4']):>6} {f(s['ev_new_pose_rate_hz']):>6}  {s['vision_loss_actions'] or '-'}")
        if s.get("mission_error"):
            print(f"     mission error: {s['mission_error']}")
        cases[seed] = {k: s.get(k) for k in (
            "waypoints_reached", "waypoints_total", "collisions", "min_clearance_m", "ekf_vs_truth_error_m_p95",
            "ekf_vs_truth_error_m_p95_with_slam_loss",
            "ekf_vs_truth_height_error_m_p95", "slam_vs_truth_error_m_p95", "ev_rate_hz_at_px4",
            "ev_new_pose_rate_hz", "vision_loss_actions", "frame_alignment", "scan_gaps", "mission_error")}
        if "slam_loss" in s:
            cases[seed]["slam_loss"] = s["slam_loss"]
    slam_loss: dict[str, Any] | None = None
    losses = [(seed, s) for seed, s in loss_flights.items() if "slam_loss" in s]
    if losses:
        injected = [(seed, s) for seed, s in losses if s["slam_loss"].get("injected")]

        def settled(s: dict[str, Any]) -> bool:
            acts = s["vision_loss_actions"].split(",")
            return "hold" in acts and acts[-1] in ("resume", "land")

        slam_loss = {
            # Rooms whose flight reached its second leg, where the camera stopped.
            "rooms_injected": [seed for seed, _ in injected],
            "held": all(bool(s["slam_loss"].get("held")) for _, s in injected) if injected else None,
            "hold_drift_m_max": round(max((float(s["slam_loss"].get("hold_drift_m", 0.0)) for _, s in injected),
                                          default=0.0), 3) if injected else None,
            "collisions": sum(s["collisions"] for _, s in injected) if injected else None,
            "resumed_or_landed": all(settled(s) for _, s in injected) if injected else None,
            # Landed during the loss: how far from where the SLAM was lost it touched down.
            "landing_drift_m_max": max((float(s["slam_loss"]["landing_drift_m"]) for _, s in injected
                                        if "landing_drift_m" in s["slam_loss"]), default=None),
            "touchdown_after_loss_s": [s["slam_loss"].get("touchdown_after_loss_s") for _, s in injected],
        }
        print(f"\nSLAM lost {slam_loss_s:g} s after the first leg: {slam_loss}")
    for seed, s in flights:
        if s["waypoints_reached"] < s["waypoints_total"] or s["collisions"]:
            print(f"\nPX4 log, room {seed}:")
            for line in s.get("px4_log_events", [])[-15:]:
                print(f"  {line}")

    def vals(key: str, of: dict[str, dict[str, Any]] = rooms) -> list[float]:
        return [float(s[key]) for s in of.values() if s.get(key) is not None]

    ekf, slam, ev = vals("ekf_vs_truth_error_m_p95"), vals("slam_vs_truth_error_m_p95"), vals("ev_rate_hz_at_px4")
    with_loss = vals("ekf_vs_truth_error_m_p95_with_slam_loss", loss_flights)
    figures = {
        "rooms": len(rooms),
        "waypoints_reached": sum(s["waypoints_reached"] for s in rooms.values()),
        "waypoints_total": sum(s["waypoints_total"] for s in rooms.values()),
        "collisions": sum(s["collisions"] for _, s in flights),
        "ekf_vs_truth_error_m_p95": max(ekf) if ekf else None,
        "ekf_vs_truth_error_m_p95_with_slam_loss": max(with_loss) if with_loss else None,
        "slam_vs_truth_error_m_p95": max(slam) if slam else None,
        "ev_rate_hz_at_px4": round(float(np.min(ev)), 1) if ev else None,
        "targets": {"ekf_vs_truth_error_m_p95": EKF_TARGET_M, "ev_rate_hz_at_px4": EV_TARGET_HZ},
        "slam_loss_3s" if slam_loss_s == SLAM_LOSS_S else f"slam_loss_{slam_loss_s:g}s": slam_loss,
        "load_avg_1min": [round(load0[0], 1), round(load1[0], 1)],
        "camera": camera,
        "rooms_detail": cases,
    }
    print(json.dumps(figures, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
