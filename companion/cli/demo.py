"""``companion demo --out DIR``: the whole system flying a mission through the simulated room.

The mock autopilot, the simulated RealSense in the seeded furnished room, the full service
(detector, tracker, semantic map, planner process, offboard), a real Mosquitto when it is
installed, and a mission uploaded with MAVSDK that crosses the room. ``--scripted`` runs the
earlier foundation demo instead (a scripted flight rendered into frame pictures).
"""

from __future__ import annotations

import argparse
import asyncio
import logging

from companion.config import CompanionConfig, load_config
from semmap.errors import PerceptionError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "demo", help="fly a MAVSDK-uploaded mission through the simulated room with the whole service",
        description="Start the mock autopilot and the simulated camera in the seeded room of the "
        "config, upload a mission crossing the room with MAVSDK and fly it with the full service "
        "(semantic map + planner + offboard). Writes the map picture with the flown path, the ROS "
        "map files, objects.json, the flight log, the effective config and summary.json into --out.",
    )
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--seed", type=int, default=None, help="room seed (overrides sim.seed)")
    # The shipped model is the default so the demo runs the real neural-network path (issue 9);
    # a model that is missing or does not load is an error naming it, not a silent oracle.
    p.add_argument("--detector", choices=("auto", "onnx", "oracle"), default="onnx",
                   help="onnx (default): the shipped builtin:furniture model (or detector.model_path); "
                   "oracle: the simulator's noisy oracle detector; auto: the model if it loads, else the oracle")
    p.add_argument("--no-broker", action="store_true", help="do not start Mosquitto (no ground link)")
    p.add_argument("--timeout", type=float, default=170.0, help="give up the mission after this many seconds")
    p.add_argument("--autopilot", default="mock", metavar="mock|px4-sitl|URL",
                   help="who flies: mock (default), the in-process mock PX4; px4-sitl, real PX4 SITL "
                   "started from ../shared/px4-sitl (or $COMPANION_PX4_SITL) on free ports; or the MAVLink "
                   "URL of an autopilot already running (the service's link, e.g. udpin://0.0.0.0:14540)")
    p.add_argument("--gcs-url", default=None,
                   help="with --autopilot URL: where MAVSDK uploads the mission (default udpin://0.0.0.0:14550, "
                   "the port PX4's GCS link sends to)")
    p.add_argument("--scripted", action="store_true",
                   help="the foundation demo: a scripted flight rendered into frame pictures")
    p.add_argument("--frames", type=int, default=40, help="--scripted: frames to render (default 40)")
    p.add_argument("--pictures", type=int, default=4, help="--scripted: frames written as pictures (default 4)")
    p.set_defaults(func=_run)


def choose_detector(cfg: CompanionConfig, which: str) -> CompanionConfig:
    """``cfg`` with the demo's detector: ``onnx``, the configured model (``builtin:furniture``
    unless the config names another), an error if it does not load; ``oracle``, the
    simulator's; ``auto``, the model when it loads, else the oracle with a warning."""
    oracle = cfg.model_copy(update={"detector": cfg.detector.model_copy(update={"kind": "oracle"})})
    if which == "oracle":
        return oracle
    from semmap.detection import detector_from_config, resolve_model_path

    model_path = resolve_model_path(cfg.detector.model_path, real_camera=False) or "builtin:furniture"
    onnx = cfg.model_copy(update={"detector": cfg.detector.model_copy(
        update={"kind": "onnx", "model_path": model_path})})

    try:
        detector_from_config(onnx.detector, [c.name for c in onnx.classes])
    except PerceptionError as exc:
        if which == "onnx":
            raise
        log.warning("the configured detector is not usable (%s): the demo uses the simulator's oracle", exc)
        return oracle
    return onnx


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if args.seed is not None:
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": args.seed})})
    if args.scripted:
        return _scripted(cfg, args)
    from companion.sim.demo_e2e import run_e2e

    cfg = choose_detector(cfg, args.detector)
    if args.autopilot != "mock":
        return _real_autopilot(cfg, args)
    result = asyncio.run(run_e2e(cfg, args.out, use_broker=not args.no_broker, timeout_s=args.timeout))
    s = result.summary
    print(f"demo: room seed {s['seed']}, detector {cfg.detector.kind}, "
          f"{s['waypoints_reached']}/{s['waypoints_total']} waypoints reached, {s['collisions']} collisions, "
          f"min clearance {s['min_clearance_m']} m, {len(s['objects_found'])} objects mapped "
          f"({s['objects_true']} in the room), longest setpoint gap {s['setpoint_gaps']['max_ms']} ms, "
          f"{s['elapsed_s']} s")
    if s.get("mission_error"):
        print(f"mission error: {s['mission_error']}")
    print(f"outputs in {result.out_dir}:")
    for role in ("picture", "map_picture", "map_map_yaml", "map_costmap_yaml", "map_objects", "summary", "config"):
        if role in result.files:
            print(f"  {role}: {result.files[role]}")
    print(f"  flight log: {result.out_dir / 'flight_log.csv'}")
    return 0 if s["waypoints_reached"] == s["waypoints_total"] and not s.get("mission_error") else 1


def _real_autopilot(cfg: CompanionConfig, args: argparse.Namespace) -> int:
    """The demo flown by PX4 SITL started here, or by the autopilot on the URL ``--autopilot``."""
    from companion.sim.demo_px4 import DEFAULT_GCS_URL, fly_px4
    from companion.sim.px4_sitl import Px4Sitl

    timeout = max(args.timeout, 240.0)
    if args.autopilot == "px4-sitl":
        s = cfg.sim
        with Px4Sitl(home_lat_lon_alt=(s.home_lat_deg, s.home_lon_deg, s.home_alt_m)) as sitl:
            print(f"PX4 SITL instance {sitl.instance} ready after {sitl.ready_after_s:.0f} s "
                  f"(onboard {sitl.onboard_url}, GCS {sitl.gcs_url})")
            flight = asyncio.run(fly_px4(cfg, args.out, sitl=sitl, use_broker=not args.no_broker, timeout_s=timeout))
    else:
        from companion.errors import DataError, LinkError
        from companion.mavlink.urls import parse_url

        try:
            parse_url(args.autopilot)
        except LinkError as exc:
            raise DataError(f"--autopilot: {exc}") from exc
        flight = asyncio.run(fly_px4(cfg, args.out, link_url=args.autopilot, gcs_url=args.gcs_url or DEFAULT_GCS_URL,
                                     use_broker=not args.no_broker, timeout_s=timeout))
    s = flight.summary
    rates = ", ".join(f"{t} {v['median']} Hz" for t, v in s.get("px4_uorb_hz", {}).items())
    print(f"demo ({s['autopilot']}): room seed {s['seed']}, detector {cfg.detector.kind}, "
          f"{s['waypoints_reached']}/{s['waypoints_total']} waypoints reached, {s['collisions']} collisions, "
          f"min clearance {s['min_clearance_m']} m, {len(s['objects_found'])} objects mapped "
          f"({s['objects_true']} in the room), {s['elapsed_s']} s" + (f"; PX4 sees {rates}" if rates else ""))
    if s.get("mission_error"):
        print(f"mission error: {s['mission_error']}")
    print(f"outputs in {flight.out_dir}:")
    for role in ("picture", "map_objects", "summary", "config", "px4_log"):
        if role in flight.files:
            print(f"  {role}: {flight.files[role]}")
    return 0 if s["waypoints_reached"] == s["waypoints_total"] and not s.get("mission_error") else 1


def _scripted(cfg: CompanionConfig, args: argparse.Namespace) -> int:
    from companion.sim.demo import run_demo  # the renderer needs the 'sim' extra

    result = run_demo(cfg, args.out, n_frames=args.frames, n_pictures=args.pictures)
    s = result.summary
    print(f"demo: room seed {s['seed']}, {len(s['objects'])} objects, "
          f"{s['frames']['rendered']} frames rendered, flight {s['flight']['duration_s']} s")
    print(f"outputs in {result.out_dir}:")
    for role in ("ground_truth_map", "summary", "config"):
        print(f"  {role}: {result.files[role]}")
    frames_dir = result.out_dir / "frames"
    print(f"  frame pictures: {frames_dir} ({sum(1 for k in result.files if k.startswith('frame_'))} files)")
    return 0
