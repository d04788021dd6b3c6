"""One GPS-denied flight against PX4 SITL: the whole service flies the demo crossing while PX4's
only position is the service's SLAM pose, judged against SIH's truth.

:func:`fly_gps_denied` places the seeded room around where SIH's vehicle stands, sets PX4's
EKF origin (SET_GPS_GLOBAL_ORIGIN, what a ground station does indoors so missions have a
latitude and longitude), uploads the crossing with MAVSDK and runs the service (SLAM
localization, external vision) with the camera rendered from the truth
(:mod:`companion.sim.px4_gps_denied`). During the flight it samples PX4's uORB rate of
``vehicle_visual_odometry``, the SLAM pose and PX4's estimate; ``slam_loss_s`` > 0 stops the
camera that long once the first leg is flown. The summary holds the bench's figures.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig, write_effective_config
from companion.errors import LinkError
from companion.geo import GeoOrigin
from companion.mavlink.failsafe import OffboardState
from companion.mavsdk_client import MavsdkClient
from companion.missions import MissionPlan, Waypoint
from companion.px4 import FlightMode
from companion.service.app import CompanionService
from companion.service.checkpoint import checkpoint_path
from companion.sim.demo_e2e import _summary, crossing_waypoints_room, feasible_seed
from companion.sim.flow_sensor import FlowSensorModel
from companion.sim.odometry import OdometryDriftModel
from companion.sim.px4_gps_denied import (
    EstimateRecorder,
    GpsDeniedSitl,
    SihTruth,
    frame_alignment,
    p95,
    placement_around_start,
)
from companion.sim.px4_sitl import Px4SitlError
from companion.sim.sim_world import SharedSimState
from semmap.slam.pose2d import from_matrix4

log = logging.getLogger(__name__)

#: PX4's uORB rates are sampled this often in flight (seconds).
UORB_PERIOD_S = 4.0
#: The SLAM pose is sampled this often (seconds).
SLAM_PERIOD_S = 0.05
#: A local position farther than this from the start is PX4's while its origin moved (see
#: :func:`set_origin_until_home`), not a flight's.
MAX_LOCAL_M = 1000.0
#: New SLAM poses sent before the EKF origin is set (EKF2 fuses our vision by then).
ORIGIN_AFTER_POSES = 20
#: Above this height (m) the vehicle counts as airborne for the error figures.
AIRBORNE_M = 0.3
#: The SLAM statuses as the tracks record them (tracks.npz ``scans``).
#: How often PX4's console is read for :data:`PX4_EVENT_LINES` (s): the time each is seen.
PX4_LOG_PERIOD_S = 0.2
PX4_EVENT_LINES = r"[Ff]ailsafe|[Ll]anding|vision|invalid setpoints|Disarmed"
SCAN_STATUS_CODES = {"ok": 0, "partial_odometry": 1, "degenerate_fallback_odometry": 2, "odometry": 3}
#: After the injected SLAM loss ends, PX4's estimate is given this long (s) to take the
#: pose back (EKF2 restarts vision fusion, resets to it) before it is judged again.
LOSS_RECOVERY_S = 3.0
#: A run of scans without a matched pose at least this long counts as a gap (s): the
#: service holds after ``link.vision_lost_hold_s`` of them.
GAP_S = 0.5
#: The truth's height above the floor (m) at which the vehicle counts as touched down (its
#: body stands 0.1 m up on its landing gear).
TOUCHDOWN_M = 0.15
#: After the service commanded a SLAM-lost landing, SIH's truth is watched this long (s) for
#: the touchdown.
LANDING_WATCH_S = 20.0


def scan_gaps(scans: list[tuple[float, float, int, float]]) -> dict[str, Any]:
    """Where the matched SLAM poses stopped for :data:`GAP_S` or more: ``no_scan`` (no scan
    was published at all: the camera or the perception process stalled) or ``unmatched``
    (scans came, none matched in full), with the capture-to-publish latency of the scans."""
    if len(scans) < 2:
        return {}
    arr = np.array(scans, dtype=np.float64)
    ok_t = arr[arr[:, 2] == 0, 0]
    gaps = {"no_scan": 0, "unmatched": 0, "longest_s": 0.0}
    for a, b in zip(ok_t[:-1], ok_t[1:], strict=True):
        if b - a < GAP_S:
            continue
        inside = arr[(arr[:, 0] > a) & (arr[:, 0] < b)]
        gaps["unmatched" if len(inside) and np.max(np.diff(np.r_[a, inside[:, 0], b])) < GAP_S else "no_scan"] += 1
        gaps["longest_s"] = round(max(gaps["longest_s"], float(b - a)), 2)
    latency_ms = 1e3 * (arr[:, 1] - arr[:, 0])
    return {**gaps, "scan_rate_hz": round(float(len(arr) / max(arr[-1, 0] - arr[0, 0], 1e-9)), 1),
            "capture_to_publish_ms_p50": round(float(np.percentile(latency_ms, 50)), 1),
            "capture_to_publish_ms_p95": round(float(np.percentile(latency_ms, 95)), 1),
            "localize_ms_p95": round(float(np.percentile(arr[:, 3], 95)), 1)}


def gps_denied_config(cfg: CompanionConfig, out: Path, link_url: str) -> CompanionConfig:
    """``cfg`` for a flight on the SLAM pose: SLAM localization, external vision as PX4's only
    position source, no MQTT."""
    return cfg.model_copy(update={
        "service": cfg.service.model_copy(update={"localization": "slam", "output_dir": str(out),
                                                  "map_dir": str(out / "checkpoint")}),
        "link": cfg.link.model_copy(update={"url": link_url, "external_vision": True,
                                            "vision_is_position_source": True}),
        "mqtt": cfg.mqtt.model_copy(update={"enabled": False}),
    })


async def set_origin_until_home(svc: CompanionService, origin: GeoOrigin) -> None:
    """Once EKF2 fuses our vision, SET_GPS_GLOBAL_ORIGIN every 3 s until PX4 reports a home.

    Two quirks of PX4 (v1.16 SITL) set the order and the altitude: without an earlier origin
    it takes the vehicle to be at latitude/longitude 0/0 and altitude 0, so a new origin
    moves its local position by thousands of kilometres and its local z by the origin's
    altitude. Sent after vision fusion has started, EKF2 resets its position to our pose
    within a second (its vision fusion fails, then resets) and the SLAM's map frame, anchored
    on PX4's frame at the first scan, is a sane one; at altitude 0 the height stays (heights
    are relative to home anyway)."""
    v = svc.vehicle
    assert v is not None
    while True:
        stream = svc.localization.stream
        if stream is not None and stream.sent_new >= ORIGIN_AFTER_POSES:
            break
        await asyncio.sleep(0.2)
    while v.snapshot().home is None:
        with contextlib.suppress(LinkError):
            v.link.send(v.link.mav.set_gps_global_origin_encode(
                v.cfg.target_system, int(origin.lat_deg * 1e7), int(origin.lon_deg * 1e7), 0, int(time.time() * 1e6)))
        await asyncio.sleep(3.0)
    log.info("GPS-denied flight: PX4 has a home position (EKF origin set)")


async def fly_gps_denied(cfg: CompanionConfig, out_dir: str | Path, sitl: GpsDeniedSitl, *,
                         timeout_s: float = 240.0, slam_loss_s: float = 0.0,
                         odometry: OdometryDriftModel | None = None,
                         flow: FlowSensorModel | None = None) -> dict[str, Any]:
    """Fly the demo crossing on the SLAM pose with ``sitl`` (started, not necessarily ready);
    returns the summary (also ``summary.json`` in ``out_dir``). ``odometry``: an odometry
    sensor of the vehicle's own for the SLAM's motion prior; ``flow``: a flow sensor wired to
    PX4 (``sitl`` started with :data:`~companion.sim.flow_sensor.FLOW_PX4_PARAMS`; see
    :class:`SihTruth`)."""
    out = Path(out_dir)
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    t_start = time.monotonic()
    cfg = gps_denied_config(await asyncio.to_thread(feasible_seed, cfg), out, sitl.onboard_url)
    with contextlib.suppress(FileNotFoundError):
        checkpoint_path(cfg).unlink()  # a fresh room: no earlier map
    placement = placement_around_start(cfg)
    x0, y0 = placement.room_to_map_xy((0.0, 0.0))
    x1, y1 = placement.room_to_map_xy((placement.room.width_m, placement.room.depth_m))
    cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"geofence_xy_m": (x0, y0, x1, y1)})})
    write_effective_config(cfg, out)
    s = cfg.sim
    origin = GeoOrigin(s.home_lat_deg, s.home_lon_deg, 0.0)
    wps_map = [placement.room_to_map_xy(w) for w in await asyncio.to_thread(crossing_waypoints_room, placement, cfg)]
    est = EstimateRecorder(cfg.link.target_system)
    # Our s, x, y, yaw (rad), generation, loop closures, odometry scale error, heading drift (rad/s).
    slam: list[tuple[float, ...]] = []
    scans: list[tuple[float, float, int, float]] = []  # capture s, published s, status code, localize ms
    uorb_hz: list[float] = []
    new_pose_rate: list[float] = []
    loss: dict[str, Any] = {}
    loss_window: list[float] = []  # our s: the camera stopped, and the recovery after it ended
    px4_events: list[tuple[float, str]] = []  # our s when seen, PX4 console line (its log has no clock)
    if odometry is not None:
        # The frames carry the sensor's odometry, which PX4's estimate does not contain.
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"camera_pose": "autopilot"}),
                                     "link": cfg.link.model_copy(update={"vision_odometry_independent": True})})
    async with SihTruth(sitl.display_url, placement, SharedSimState(), odometry, flow) as truth:
        await asyncio.to_thread(sitl.stream_truth)
        await truth.wait_first()
        plan = MissionPlan(tuple(Waypoint(xyz_map_m=(x, y, cfg.planner.flight_altitude_m), acceptance_radius_m=0.3)
                                 for x, y in wps_map), origin, "GPS-denied crossing")
        async with MavsdkClient(sitl.gcs_url, connect_timeout_s=30.0) as client:
            await client.upload_mission(plan)
        service = CompanionService(cfg, truth.frame_source(cfg), out_dir=out, fly_mission=True,
                                   object_classes={o.object_id: o.class_name for o in placement.room.objects})
        stop = asyncio.Event()

        async def sample_slam() -> None:
            while True:
                st = service.localization.latest()
                if st is not None and (not scans or scans[-1][0] != st.stamp_s):
                    scans.append((st.stamp_s, time.monotonic() - st.age_s, SCAN_STATUS_CODES.get(st.status, -1),
                                  st.localize_ms))
                    if st.status == "ok":
                        slam.append((st.stamp_s, *(float(v) for v in from_matrix4(st.T_map_body)),
                                     float(st.generation), float(st.loop_closures), st.odometry_scale_error,
                                     st.odometry_heading_drift_rad_s))
                await asyncio.sleep(SLAM_PERIOD_S)

        async def sample_uorb() -> None:
            last: tuple[float, int] | None = None
            while True:
                await asyncio.sleep(UORB_PERIOD_S)
                v, stream = service.vehicle, service.localization.stream
                if v is None or stream is None or v.snapshot().flight_mode is not FlightMode.OFFBOARD:
                    last = None
                    continue
                try:
                    uorb_hz.append((await asyncio.to_thread(sitl.uorb_top_hz, ["vehicle_visual_odometry"]))
                                   ["vehicle_visual_odometry"])
                except Px4SitlError as exc:
                    log.warning("uorb top failed: %s", exc)
                now = (time.monotonic(), stream.sent_new)
                if last is not None:
                    new_pose_rate.append((now[1] - last[1]) / (now[0] - last[0]))
                last = now

        async def lose_slam() -> None:
            def flying_second_leg() -> bool:
                v, r = service.vehicle, service.runner
                return (v is not None and r is not None and len(r.reports) >= 1
                        and v.offboard.state is OffboardState.ACTIVE)
            while True:
                if flying_second_leg():
                    break
                await asyncio.sleep(0.05)
            truth.shared.camera_missing = True
            loss["injected"] = True
            t0, held_xy = time.monotonic(), None
            loss_window.append(t0)
            log.warning("GPS-denied flight: the camera stops for %.1f s (SLAM lost)", slam_loss_s)
            while time.monotonic() - t0 < slam_loss_s:
                await asyncio.sleep(0.05)
                v = service.vehicle
                if held_xy is None and v is not None and v.offboard.state is OffboardState.HOLDING:
                    held_xy = (time.monotonic(), truth.path_map_m()[-1, :2].copy())
                    loss["held"] = True  # now: a landing during the loss ends the flight and this task
                if held_xy is not None and time.monotonic() - held_xy[0] > 1.0:
                    drift = float(np.linalg.norm(truth.path_map_m()[-1, :2] - held_xy[1]))
                    loss["hold_drift_m"] = max(loss.get("hold_drift_m", 0.0), drift)
            truth.shared.camera_missing = False
            loss_window.append(time.monotonic() + LOSS_RECOVERY_S)
            loss.setdefault("held", False)

        async def watch_px4_log() -> None:
            offset = len(sitl.log_text())
            while True:
                await asyncio.sleep(PX4_LOG_PERIOD_S)
                text = sitl.log_text()
                now = time.monotonic()
                px4_events.extend((now, ln) for ln in text[offset:].splitlines() if re.search(PX4_EVENT_LINES, ln))
                offset = len(text)

        async def on_active(svc: CompanionService) -> None:
            v = svc.vehicle
            assert v is not None
            truth.to_local = v.autopilot_clock.to_local
            est.attach(v.link)
            truth.follow_estimate(v.link, v.cfg.target_system)
            tasks = [set_origin_until_home(svc, origin), sample_slam(), sample_uorb(), watch_px4_log()]
            if slam_loss_s > 0.0:
                tasks.append(lose_slam())
            await asyncio.gather(*tasks)

        async def stopper() -> None:
            try:
                await asyncio.wait_for(service.mission_done.wait(), timeout_s)
            except TimeoutError:
                log.error("GPS-denied flight: the mission did not finish within %.0f s", timeout_s)
            stop.set()

        service.on_active = on_active
        async with asyncio.TaskGroup() as tg:
            tg.create_task(stopper())
            report = await service.run(stop)
            stop.set()
        loss_actions = report.localization.get("vision_loss_actions", "")
        if "land" in loss_actions:
            # The service stops once it has commanded the landing; PX4 flies it on.
            await until_touchdown(truth, LANDING_WATCH_S)
    summary = _summary(cfg, placement, report, truth.path_map_m(), wps_map, [], service, time.monotonic() - t_start)
    for k in ("setpoint_gaps", "setpoints_received", "stage_timings_ms", "objects_found", "checkpoints"):
        summary.pop(k, None)
    # A landing during the loss ends the flight before the loss does: judged apart to the end.
    window = (loss_window[0], loss_window[1] if len(loss_window) == 2 else math.inf) if loss_window else None
    summary.update(judge(truth, est, slam, window))
    if window is not None:
        with_loss = judge(truth, est, slam)
        summary["ekf_vs_truth_error_m_p95_with_slam_loss"] = with_loss["ekf_vs_truth_error_m_p95"]
        summary["slam_vs_truth_error_m_p95_with_slam_loss"] = with_loss["slam_vs_truth_error_m_p95"]
    summary["ev_rate_hz_at_px4"] = round(float(np.median(uorb_hz)), 1) if uorb_hz else None
    summary["ev_new_pose_rate_hz"] = round(float(np.median(new_pose_rate)), 1) if new_pose_rate else None
    summary["localization"] = report.localization
    summary["scan_gaps"] = scan_gaps(scans)
    summary["vision_loss_actions"] = loss_actions
    summary["optical_flow_sent"] = truth.flow_sent
    if slam_loss_s > 0.0:
        if loss_window and "land" in loss_actions:
            # A resumed flight's touchdown is the mission's own landing, not the loss's.
            loss.update(landing_after_loss(truth.samples, loss_window[0]))
        if loss_window:
            # When PX4 said what, counted from the camera's stop (within a poll period).
            loss["px4_events_after_loss_s"] = [(round(t - loss_window[0], 1), ln.strip())
                                               for t, ln in px4_events if t >= loss_window[0]]
        summary["slam_loss"] = {"seconds": slam_loss_s, **loss}
    summary["px4_log_events"] = sitl.log_lines_since(0, r"WARN|ERROR|Armed|Disarmed|[Ll]anding|[Tt]akeoff|"
                                                        r"[Ff]ailsafe|[Oo]ffboard|vision|EV |reset")[-40:]
    (out / "px4.log").write_text(sitl.log_text(), encoding="utf-8")
    # The tracks the figures come from, for a look afterwards (our clock, map frames unaligned).
    np.savez_compressed(out / "tracks.npz", truth=np.array([(t.local_s, t.x_m, t.y_m, t.z_m, t.yaw_rad, t.roll_rad,
                                                             t.pitch_rad) for t in truth.samples]).reshape(-1, 7),
                        px4_estimate=np.array(est.rows).reshape(-1, 5), slam=np.array(slam).reshape(-1, 8),
                        scans=np.array(scans).reshape(-1, 4))
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n", encoding="utf-8")
    return summary


async def until_touchdown(truth: SihTruth, timeout_s: float) -> None:
    """Wait until SIH's truth stands at most :data:`TOUCHDOWN_M` above the floor, or
    ``timeout_s`` (then a warning)."""
    deadline = time.monotonic() + timeout_s
    while not truth.samples or truth.samples[-1].z_m > TOUCHDOWN_M:
        if time.monotonic() > deadline:
            log.warning("GPS-denied flight: no touchdown within %.0f s of the service's end", timeout_s)
            return
        await asyncio.sleep(0.1)


def landing_after_loss(samples: list[Any], lost_at_s: float) -> dict[str, Any]:
    """Where the vehicle touched down after the SLAM was lost at ``lost_at_s`` (our clock), by
    SIH's truth: ``landing_drift_m`` horizontally from where it was at the loss, and
    ``touchdown_after_loss_s``; empty when it did not land."""
    arr = np.array([(t.local_s, t.x_m, t.y_m, t.z_m) for t in samples], dtype=np.float64).reshape(-1, 4)
    after = arr[arr[:, 0] >= lost_at_s]
    if len(after) == 0 or after[0, 3] <= TOUCHDOWN_M:
        return {}
    down = np.flatnonzero(after[:, 3] <= TOUCHDOWN_M)
    if len(down) == 0:
        return {}
    t = after[int(down[0])]
    return {"landing_drift_m": round(float(np.hypot(t[1] - after[0, 1], t[2] - after[0, 2])), 3),
            "touchdown_after_loss_s": round(float(t[0] - lost_at_s), 2),
            "height_at_loss_m": round(float(after[0, 3]), 2)}


def judge(truth: SihTruth, est: EstimateRecorder, slam: list[tuple[float, ...]],
          exclude_s: tuple[float, float] | None = None) -> dict[str, Any]:
    """PX4's estimate (at its arrival) and the SLAM pose (at its capture) against SIH's truth
    interpolated to those instants, airborne samples outside ``exclude_s`` (our clock: the
    injected SLAM loss and its recovery, judged by the hold instead), after aligning
    the frames on the ground before take-off (:func:`frame_alignment`)."""
    if len(truth.samples) < 2 or len(est.rows) < 10:
        return {"ekf_vs_truth_error_m_p95": None, "slam_vs_truth_error_m_p95": None}
    e = np.array(est.rows, dtype=np.float64)
    e = e[np.hypot(e[:, 1], e[:, 2]) < MAX_LOCAL_M]  # PX4's local position while its origin was being set
    e = e[(e[:, 0] >= truth.samples[0].local_s) & (e[:, 0] <= truth.samples[-1].local_s) & np.isfinite(e[:, 4])]
    t_at_e = truth.at(e[:, 0], "local")
    airborne = t_at_e[:, 2] > AIRBORNE_M
    judged = airborne & ~_inside(e[:, 0], exclude_s)
    first_air = int(np.argmax(airborne)) if airborne.any() else len(e)
    ground = np.arange(max(0, first_air - 60), max(0, first_air - 10))  # at rest, vision fused, not yet climbing
    if len(ground) < 5:
        return {"ekf_vs_truth_error_m_p95": None, "slam_vs_truth_error_m_p95": None}
    align = frame_alignment(np.column_stack([e[ground, 1:3], e[ground, 3], e[ground, 4]]), t_at_e[ground])
    ekf_xy = np.linalg.norm(align.apply(e[judged, 1:3]) - t_at_e[judged, :2], axis=1)
    # Height: PX4's z above where it stood against the truth's height above the floor.
    z0 = float(np.mean(e[ground, 3] - t_at_e[ground, 2]))
    ekf_z = np.abs(e[judged, 3] - z0 - t_at_e[judged, 2])
    out: dict[str, Any] = {"ekf_vs_truth_error_m_p95": p95(ekf_xy), "ekf_vs_truth_error_m_max":
                           round(float(ekf_xy.max()), 3) if ekf_xy.size else None,
                           "ekf_vs_truth_height_error_m_p95": p95(ekf_z),
                           "frame_alignment": {"yaw_deg": round(math.degrees(align.yaw_rad), 2),
                                               "xy_m": [round(float(v), 3) for v in align.t_xy_m]}}
    if slam:
        sl = np.array(slam, dtype=np.float64)
        sl = sl[(sl[:, 0] >= truth.samples[0].local_s) & (sl[:, 0] <= truth.samples[-1].local_s)]
        t_at_s = truth.at(sl[:, 0], "local")
        air = (t_at_s[:, 2] > AIRBORNE_M) & ~_inside(sl[:, 0], exclude_s)
        err = np.linalg.norm(align.apply(sl[air, 1:3]) - t_at_s[air, :2], axis=1)
        out["slam_vs_truth_error_m_p95"] = p95(err)
    else:
        out["slam_vs_truth_error_m_p95"] = None
    return out


def _inside(t_s: NDArray[np.float64], window_s: tuple[float, float] | None) -> NDArray[np.bool_]:
    if window_s is None:
        return np.zeros(len(t_s), dtype=bool)
    return (t_s >= window_s[0]) & (t_s <= window_s[1])
