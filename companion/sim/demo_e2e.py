"""The end-to-end demo: the whole service flying a MAVSDK-uploaded mission through a simulated room.

In one process: the mock autopilot and the simulated RealSense in the seeded furnished room
(:class:`~companion.sim.sim_world.SimWorld`), a real Mosquitto broker when the binary is
installed, and the full :class:`~companion.service.app.CompanionService` (detector, tracker,
semantic map, planner process, offboard). A mission that crosses the room - waypoints only,
knowing nothing of the furniture - is uploaded with MAVSDK; the service downloads it and flies
it leg by leg with the semantic planner, then lands. Everything is judged against the
simulator's ground truth (:mod:`companion.sim.groundtruth`) and written into the output folder.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import logging
import math
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig, write_effective_config
from companion.errors import SimulationError
from companion.px4 import FlightMode
from companion.service.app import CompanionService, ServiceReport
from companion.sim.demo_flight import (
    export_flight,
    flight_config,
    upload_crossing,
    with_room_geofence,
    write_summary,
)
from companion.sim.groundtruth import (
    clearance_m,
    collides,
    densify,
    ground_truth_planner,
)
from companion.sim.sim_world import START_INSIDE_M, SimPlacement, SimWorld, start_point_room_m
from companion.sim.world import Room
from companion.sources.sim import room_from_config

log = logging.getLogger(__name__)

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
#: How long a run waits for a landing the service commanded to touch down (the mock lands at 0.7 m/s).
LANDING_TIMEOUT_S = 30.0
#: Planning time for each candidate leg when a mission is chosen on the true map.
SETUP_PLAN_TIME_LIMIT_S = 10.0


@dataclass
class E2EResult:
    """What an end-to-end run produced."""

    out_dir: Path
    summary: dict[str, Any] = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    report: ServiceReport | None = None


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LocalBroker:
    """A Mosquitto broker on a free loopback port; ``stop()`` and ``start()`` again keep the port
    (fault tests restart it under connected clients)."""

    def __init__(self, workdir: Path) -> None:
        self.port = _free_tcp_port()
        self.workdir = workdir
        self._proc: subprocess.Popen[bytes] | None = None
        self.conf = workdir / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n",
                             encoding="utf-8")

    def start(self, timeout_s: float = 5.0) -> None:
        """Start the broker and wait until it accepts connections."""
        with (self.workdir / "mosquitto.log").open("a") as out:
            self._proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.05)
        log.warning("mosquitto did not accept connections on %d within %.0f s", self.port, timeout_s)

    def stop(self) -> None:
        """Stop the broker (it loses every session and retained message)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        proc.terminate()
        try:
            proc.wait(3.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(1.0)


@contextlib.contextmanager
def local_broker(workdir: Path) -> Iterator[LocalBroker | None]:
    """A running :class:`LocalBroker`, or None when Mosquitto is not installed."""
    if not Path(MOSQUITTO).exists():
        log.warning("mosquitto not installed: the demo runs without the ground link")
        yield None
        return
    broker = LocalBroker(workdir)
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


def crossing_waypoints_room(placement: SimPlacement, cfg: CompanionConfig) -> list[tuple[float, float]]:
    """Mission waypoints (room frame) across the room and back: the middle of the room (the
    free point nearest to it), just inside the far doorway, the middle again and the start. They keep clear of everything in the
    ground truth, but the straight legs between them cross furniture freely: the mission
    author knows the room's doorways, not its furniture."""
    room = placement.room
    # Where the vehicle stands, not the map origin: on PX4 a landing away from home moves them apart.
    start = start_point_room_m(room)
    if len(room.doorways) >= 2:
        goal = room.doorways[1].inside_point_m(START_INSIDE_M)
    else:
        goal = (room.width_m - start[0], room.depth_m - start[1])
    p = cfg.planner
    margins = {c.name: c.margin_m for c in cfg.classes}
    xs, ys = np.meshgrid(np.arange(0.5, room.width_m - 0.5, 0.1), np.arange(0.5, room.depth_m - 0.5, 0.1))
    cand = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, p.flight_altitude_m)])
    # Clear of walls and of every object's whole footprint (with its class margin), as the
    # semantic map will see them; a waypoint under a table would be unreachable.
    ok = clearance_m(placement.room, cand, 2.0 * p.flight_altitude_m) >= p.keepout_m() + 0.3
    for o in room.objects:
        poly = o.footprint_xy_m().astype(np.float32)
        need = p.keepout_m(margins.get(o.class_name, 0.0)) + 0.3
        d = np.array([-cv2.pointPolygonTest(poly, (float(x), float(y)), True) for x, y in cand[:, :2]])
        ok &= d >= need
    if not np.any(ok):
        raise SimulationError(f"room seed {room.seed}: no free point for a mission waypoint")
    mid_target = np.array([room.width_m / 2.0, room.depth_m / 2.0])
    free = cand[ok, :2]
    order = np.argsort(np.linalg.norm(free - mid_target, axis=1))
    # Choosing a mission is set-up, not flight: a loaded machine must not make a room infeasible.
    planner = ground_truth_planner(room, cfg, time_limit_s=max(cfg.planner.time_limit_s, SETUP_PLAN_TIME_LIMIT_S))
    goal_xy = (float(goal[0]), float(goal[1]))
    start_xy = (float(start[0]), float(start[1]))
    best: tuple[int, tuple[float, float]] | None = None
    for k in order[:90:3]:
        mid = (float(free[k, 0]), float(free[k, 1]))
        # Our planner, with the class margins, has a path through it on the true semantic map.
        if not (planner.plan(start, mid).ok and planner.plan(mid, goal).ok):
            continue
        # Prefer waypoints whose straight legs run into furniture: the planner must go around.
        crossed = _objects_crossed(room, [start_xy, mid, goal_xy])
        if best is None or crossed > best[0]:
            best = (crossed, mid)
        if crossed >= 2:
            break
    if best is not None:
        mid = best[1]
        # Across and back: the return legs fly through the map built on the way out.
        return [mid, goal_xy, mid, start_xy]
    raise SimulationError(f"room seed {room.seed}: no reachable mid-room waypoint")


def _objects_crossed(room: Room, polyline_xy_m: list[tuple[float, float]]) -> int:
    """How many objects' footprints the straight polyline passes over."""
    pts = densify(np.asarray(polyline_xy_m, dtype=np.float64), 0.05)
    n = 0
    for o in room.objects:
        poly = o.footprint_xy_m().astype(np.float32)
        if any(cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in pts):
            n += 1
    return n


def feasible_seed(cfg: CompanionConfig, tries: int = 20) -> CompanionConfig:
    """``cfg`` with the first room seed from ``sim.seed`` on whose true map the crossing
    mission is feasible for our planner (logged when it differs)."""
    seed = cfg.sim.seed
    for s in range(seed, seed + tries):
        c = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": s})})
        room = room_from_config(c)
        try:
            crossing_waypoints_room(SimPlacement(room, start_point_room_m(room)), c)
        except SimulationError as exc:
            log.warning("room seed %d: %s; trying seed %d", s, exc, s + 1)
            continue
        return c
    raise SimulationError(f"no room seed in {seed}..{seed + tries - 1} has a feasible crossing")


def setpoint_gap_stats_ms(stamps_s: list[float], offboard_gap_max_s: float = 0.0) -> dict[str, float | int]:
    """The distribution of gaps between consecutive received setpoints (autopilot receive
    times, seconds): ``{"p50_ms", "p99_ms", "max_ms", "over_100ms", "offboard_max_ms"}`` (zeros
    for fewer than two). ``offboard_gap_max_s``: the autopilot's own longest gap in OFFBOARD,
    which also counts a stream that stopped and never resumed; ``max_ms`` is the longer of the two."""
    off_ms = round(1e3 * offboard_gap_max_s, 1)
    if len(stamps_s) < 2:
        return {"p50_ms": 0.0, "p99_ms": 0.0, "max_ms": off_ms, "over_100ms": int(off_ms > 100.0),
                "offboard_max_ms": off_ms}
    gaps_ms = 1e3 * np.diff(np.asarray(sorted(stamps_s)))
    return {"p50_ms": round(float(np.percentile(gaps_ms, 50)), 1),
            "p99_ms": round(float(np.percentile(gaps_ms, 99)), 1),
            "max_ms": max(round(float(np.max(gaps_ms)), 1), off_ms),
            "over_100ms": max(int(np.count_nonzero(gaps_ms > 100.0)), int(off_ms > 100.0)),
            "offboard_max_ms": off_ms}


async def run_e2e(cfg: CompanionConfig, out_dir: str | Path, *, use_broker: bool = True,
                  timeout_s: float = 170.0, inject: Any = None) -> E2EResult:
    """Fly the demo mission with the whole service; write outputs into ``out_dir``.

    ``inject``: optional ``async (world, service, broker) -> None`` run once the service is active
    (fault tests). Returns the summary (also written as ``summary.json``)."""
    out = Path(out_dir)
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    result = E2EResult(out)
    t_start = time.monotonic()
    cfg = await asyncio.to_thread(feasible_seed, cfg)
    link_port, mavsdk_port = free_udp_port(), free_udp_port()
    with tempfile.TemporaryDirectory(prefix="companion-demo-") as tmp, \
            (local_broker(Path(tmp)) if use_broker else contextlib.nullcontext(None)) as broker:
        broker_port = broker.port if broker is not None else None
        cfg = flight_config(cfg, out, f"udpin://127.0.0.1:{link_port}", broker_port)
        world = SimWorld(cfg, autopilot_port=0, remote_ports=(link_port, mavsdk_port))
        cfg = with_room_geofence(cfg, world.placement)
        result.files["config"] = write_effective_config(cfg, out)
        async with world:
            placement = world.placement
            # Planning on the true map takes a few hundred ms: off the loop the mock flies on.
            wps_room = await asyncio.to_thread(crossing_waypoints_room, placement, cfg)
            wps_map = [placement.room_to_map_xy(w) for w in wps_room]
            await upload_crossing(f"udpin://127.0.0.1:{mavsdk_port}", wps_map, cfg.planner.flight_altitude_m)
            service = CompanionService(
                cfg, world.frame_source(), out_dir=out, fly_mission=True,
                object_classes={o.object_id: o.class_name for o in placement.room.objects},
            )
            stamps: list[float] = []
            flown: list[NDArray[np.float64]] = []
            stop = asyncio.Event()

            async def watch() -> None:
                last = -math.inf
                ap = world.autopilot
                while not stop.is_set():
                    for sp in list(ap.setpoints):
                        if sp.stamp_s > last:
                            stamps.append(sp.stamp_s)
                    if ap.setpoints:
                        last = ap.setpoints[-1].stamp_s
                    n, e, d = ap.position_ned_m
                    flown.append(np.array([e, n, -d]))
                    await asyncio.sleep(0.05)

            async def stopper() -> None:
                try:
                    await asyncio.wait_for(service.mission_done.wait(), timeout_s)
                except TimeoutError:
                    log.error("demo: the mission did not finish within %.0f s", timeout_s)
                # A landing the service commanded (SLAM or perception lost) ends the mission at
                # once; the run, like a completed mission, ends with the vehicle on the ground.
                ap = world.autopilot
                for _ in range(round(LANDING_TIMEOUT_S / 0.1)):
                    if not (ap.mode is FlightMode.LAND and ap.in_air):
                        break
                    await asyncio.sleep(0.1)
                stop.set()

            if inject is not None:
                service.on_active = lambda svc: inject(world, svc, broker)
            async with asyncio.TaskGroup() as tg:
                tg.create_task(watch())
                tg.create_task(stopper())
                report = await service.run(stop)
                stop.set()
    result.report = report
    path_map = np.array(flown) if flown else np.zeros((0, 3))
    result.files.update(export_flight(out, service, placement, path_map, wps_map))
    result.summary = _summary(cfg, placement, report, path_map, wps_map, stamps, service, time.monotonic() - t_start)
    # The gap the autopilot saw, open ones included (the stream to it stopped after a failsafe).
    result.summary["setpoint_gaps"] = setpoint_gap_stats_ms(stamps, world.autopilot.offboard_gap_max_s)
    result.summary["mqtt"] = broker_port is not None
    result.summary["detector"] = cfg.detector.kind
    result.summary["autopilot_failsafes"] = [str(f) for f in world.autopilot.failsafes]
    result.summary["autopilot_final"] = {"mode": world.autopilot.mode.name, "in_air": world.autopilot.in_air,
                                         "armed": world.autopilot.armed,
                                         "modes": [m.name for _, m in world.autopilot.mode_changes]}
    # What reached the autopilot from the service, by message (the obstacle feed, TIMESYNC).
    result.summary["autopilot_received"] = {
        name: world.autopilot.messages_received[name]
        for name in ("SET_POSITION_TARGET_LOCAL_NED", "OBSTACLE_DISTANCE", "TIMESYNC")}
    result.summary["map_restored"] = service.restored
    write_summary(out, result.summary, result.files)
    return result


def _summary(cfg: CompanionConfig, placement: SimPlacement, report: ServiceReport, path_map: NDArray[np.float64],
             wps_map: list[tuple[float, float]], stamps: list[float], service: CompanionService,
             elapsed_s: float) -> dict[str, Any]:
    p = cfg.planner
    airborne = path_map[path_map[:, 2] > 0.3] if len(path_map) else path_map
    room_path = placement.map_to_room(airborne) if len(airborne) else airborne
    dense = densify(room_path, 0.02) if len(room_path) >= 2 else room_path
    coll = collides(placement.room, dense, p.vehicle_radius_m, p.vehicle_height_m) if len(dense) else np.zeros(0, bool)
    clear = clearance_m(placement.room, dense, p.vehicle_height_m) if len(dense) else np.zeros(0)
    true_ids = {o.object_id: o.class_name for o in placement.room.objects}
    found = []
    assert service.smap is not None
    for fp in service.smap.objects:
        c = np.asarray(fp.polygon_xy_m).mean(axis=0) if len(fp.polygon_xy_m) else np.zeros(2)
        found.append({"id": fp.object_id, "class": fp.class_name,
                      "center_xy_m": [round(float(v), 3) for v in c]})
    return {
        "seed": placement.room.seed,
        "room_m": {"width": placement.room.width_m, "depth": placement.room.depth_m},
        "room_offset_xy_m": list(placement.offset_xy_m),
        "waypoints_xy_m": [[round(x, 3), round(y, 3)] for x, y in wps_map],
        "waypoints_reached": sum(1 for r in report.legs if r.reached),
        "waypoints_total": len(wps_map),
        "legs": [{"seq": r.seq, "reached": r.reached, "plans": r.plans, "replans_on_new_obstacle": r.replans_invalid,
                  "failed_plans": r.failed_plans, "duration_s": round(r.duration_s, 2),
                  "final_error_m": None if math.isnan(r.final_error_m) else round(r.final_error_m, 3)}
                 for r in report.legs],
        "mission_error": report.mission_error,
        "collisions": int(np.count_nonzero(coll)),
        "min_clearance_m": None if len(clear) == 0 else round(float(np.min(clear)), 3),
        "collision_points_room_xy_m": [[round(float(v), 2) for v in q[:2]] for q in dense[coll][:: max(1, int(np.count_nonzero(coll)) // 5)]][:5],
        "objects_true": len(true_ids),
        "objects_found": found,
        "setpoint_gaps": setpoint_gap_stats_ms(stamps),
        "setpoints_received": len(stamps),
        "stage_timings_ms": report.stage_timings,
        "latency_ms": report.latency,
        "plan_ms": {"mean": round(float(np.mean(report.plan_ms)), 1) if report.plan_ms else None,
                    "max": round(float(np.max(report.plan_ms)), 1) if report.plan_ms else None,
                    "count": len(report.plan_ms)},
        "frames": {"processed": report.frames_processed, "dropped": report.frames_dropped,
                   "failed": report.frames_failed, "unposed": report.frames_unposed},
        "checkpoints": report.checkpoints,
        "elapsed_s": round(elapsed_s, 1),
    }


def read_flight_log(path: Path) -> list[dict[str, str]]:
    """Rows of a flight log CSV (for tests and tools)."""
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))
