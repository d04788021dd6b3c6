"""The end-to-end demo flown by a real autopilot: PX4 SITL (started here) or one already running.

The same flight as :func:`companion.sim.demo_e2e.run_e2e` (a MAVSDK-uploaded mission across
the seeded room, flown leg by leg by the whole service: detector, map, planner, offboard),
but the vehicle is the autopilot's: PX4 flies it, and the simulated world only renders the
camera from the pose PX4 reports (:class:`~companion.sim.px4_world.Px4World`). The room is
placed around where the vehicle stands when the demo starts. Judged against the room's
ground truth like the mock demo; with a SITL started here, PX4's own view of the companion's
streams (``uorb top``) is sampled during the flight and its console log is kept.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig, write_effective_config
from companion.errors import LinkError
from companion.px4 import FlightMode
from companion.service.app import CompanionService, ServiceReport
from companion.sim.demo_e2e import _summary, crossing_waypoints_room, feasible_seed, local_broker
from companion.sim.demo_flight import (
    export_flight,
    flight_config,
    upload_crossing,
    with_room_geofence,
    write_summary,
)
from companion.sim.px4_probes import engage_check
from companion.sim.px4_sitl import Px4Sitl, Px4SitlError
from companion.sim.px4_world import FlightTimeline, Px4World, vehicle_start_map_xy

log = logging.getLogger(__name__)

#: The companion's uORB topics as PX4 sees them: its setpoints and its obstacle distances.
PX4_TOPICS = ["offboard_control_mode", "trajectory_setpoint", "obstacle_distance"]
#: How often PX4's topic rates are sampled during the flight (seconds).
UORB_PERIOD_S = 4.0
#: The default ground-station URL when the autopilot runs already (PX4's GCS link sends to 14550).
DEFAULT_GCS_URL = "udpin://0.0.0.0:14550"


@dataclass
class Px4Flight:
    """What a flight against a real autopilot produced."""

    out_dir: Path
    summary: dict[str, Any] = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    report: ServiceReport | None = None
    #: ``uorb top`` samples taken while the vehicle was in OFFBOARD: topic -> Hz per sample.
    uorb_hz: dict[str, list[float]] = field(default_factory=dict)
    #: Mode, arming and landed-state changes as PX4 reported them on the service's link.
    timeline: FlightTimeline = field(default_factory=FlightTimeline)
    #: When the service asked PX4 for OFFBOARD (monotonic seconds, as the timeline's).
    offboard_requests_s: list[float] = field(default_factory=list)


async def fly_px4(cfg: CompanionConfig, out_dir: str | Path, *, sitl: Px4Sitl | None = None,
                  link_url: str | None = None, gcs_url: str = DEFAULT_GCS_URL, use_broker: bool = True,
                  timeout_s: float = 240.0) -> Px4Flight:
    """Fly the demo mission through the seeded room with the autopilot of ``sitl`` (running)
    or the one on ``link_url`` (the service's link; MAVSDK uploads on ``gcs_url``)."""
    if sitl is not None:
        link_url, gcs_url = sitl.onboard_url, sitl.gcs_url
    if link_url is None:
        raise LinkError("fly_px4: give a running PX4 SITL or the autopilot's link URL")
    out = Path(out_dir)
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    flight = Px4Flight(out)
    t_start = time.monotonic()
    cfg = await asyncio.to_thread(feasible_seed, cfg)
    with contextlib.ExitStack() as tmp_stack:
        workdir = Path(tmp_stack.enter_context(tempfile.TemporaryDirectory(prefix="companion-px4-demo-")))
        broker = tmp_stack.enter_context(local_broker(workdir)) if use_broker else None
        cfg = flight_config(cfg, out, link_url, broker.port if broker is not None else None)
        start = await vehicle_start_map_xy(cfg.link)
        world = Px4World(cfg, start, target_system=cfg.link.target_system,
                         target_component=cfg.link.target_component)
        placement = world.placement
        flight.timeline = world.timeline
        cfg = with_room_geofence(cfg, placement)
        flight.files["config"] = write_effective_config(cfg, out)
        wps_room = await asyncio.to_thread(crossing_waypoints_room, placement, cfg)
        wps_map = [placement.room_to_map_xy(w) for w in wps_room]
        await upload_crossing(gcs_url, wps_map, cfg.planner.flight_altitude_m, connect_timeout_s=30.0)
        log.info("PX4 demo: room seed %d placed around the vehicle at (%.2f, %.2f) m; %d waypoints uploaded",
                 placement.room.seed, start[0], start[1], len(wps_map))
        service = CompanionService(cfg, world.frame_source(), out_dir=out, fly_mission=True,
                                   object_classes={o.object_id: o.class_name for o in placement.room.objects})
        stop = asyncio.Event()

        def follow(svc: CompanionService) -> None:
            # The service opens its link when it activates: the world rides on the same telemetry.
            assert svc.vehicle is not None
            world.follow(svc.vehicle.link)

        service.on_active = follow
        async def stopper() -> None:
            try:
                await asyncio.wait_for(service.mission_done.wait(), timeout_s)
            except TimeoutError:
                log.error("PX4 demo: the mission did not finish within %.0f s", timeout_s)
            stop.set()

        async def sample_uorb() -> None:
            assert sitl is not None
            while not stop.is_set():
                await asyncio.sleep(UORB_PERIOD_S)
                v = service.vehicle
                if v is None or v.snapshot().flight_mode is not FlightMode.OFFBOARD:
                    continue
                try:
                    rates = await asyncio.to_thread(sitl.uorb_top_hz, PX4_TOPICS)
                except Px4SitlError as exc:
                    log.warning("PX4 demo: uorb top failed: %s", exc)
                    continue
                for topic, hz in rates.items():
                    flight.uorb_hz.setdefault(topic, []).append(hz)

        log_offset = len(sitl.log_text()) if sitl is not None else 0
        async with asyncio.TaskGroup() as tg:
            tg.create_task(stopper())
            if sitl is not None:
                tg.create_task(sample_uorb())
            report = await service.run(stop)
            stop.set()
    flight.report = report
    path_map = world.path_map_m
    flight.files.update(export_flight(out, service, placement, path_map, wps_map))
    s = _summary(cfg, placement, report, path_map, wps_map, [], service, time.monotonic() - t_start)
    s.pop("setpoint_gaps")
    s.pop("setpoints_received")
    s["autopilot"] = "px4-sitl" if sitl is not None else link_url
    s["detector"] = cfg.detector.kind
    s["mqtt"] = broker is not None
    s["start_map_xy_m"] = [round(v, 3) for v in start]
    s["camera_poses"] = world.poses_published
    # Each plan's frame-to-setpoint latency (a flight has a handful): benchmarks pool them.
    s["frame_to_setpoint_ms"] = [round(v, 1) for v in service.runner.frame_to_setpoint_ms] \
        if service.runner is not None else []
    if service.vehicle is not None:
        flight.offboard_requests_s = list(service.vehicle.offboard.mode_requests_s)
    engaged_ok, engaged = engage_check(flight.timeline.events, cfg.planner.flight_altitude_m,
                                       path=flight.timeline.path, requests_s=flight.offboard_requests_s)
    s["engage"] = {"ok": engaged_ok, "detail": engaged}
    s["modes"] = [f"{e.mode} {'armed' if e.armed else 'disarmed'} {e.landed}" +
                  ("" if e.xyz_map_m is None else f" z={e.xyz_map_m[2]:.2f}") for e in flight.timeline.events]
    s["px4_uorb_hz"] = {t: {"median": round(float(np.median(v)), 1), "min": round(float(np.min(v)), 1),
                            "samples": len(v)} for t, v in flight.uorb_hz.items() if v}
    if sitl is not None:
        s["px4_log_events"] = sitl.log_lines_since(log_offset, r"WARN|ERROR|Armed|Disarmed|[Ll]anding|[Tt]akeoff|"
                                                                r"[Ff]ailsafe|[Oo]ffboard|mode")[-60:]
        flight.files["px4_log"] = _copy_log(sitl, out)
    flight.summary = s
    write_summary(out, s, flight.files)
    return flight


def _copy_log(sitl: Px4Sitl, out: Path) -> Path:
    dest = out / "px4.log"
    dest.write_text(sitl.log_text(), encoding="utf-8")
    return dest

