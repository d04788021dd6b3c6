"""Conformance probes against real PX4 SITL: what the companion does with PX4, checked from outside.

Each probe takes a running :class:`~companion.sim.px4_sitl.Px4Sitl` (a fresh one: the probes
leave the vehicle in odd states on purpose) and returns a :class:`ProbeResult` with what was
seen and PX4's own log lines. ``bench/px4_sitl.py`` times them and the ``px4`` tests assert
them:

* :func:`probe_mission_start`: ``companion mission upload --start`` of a mission file (the
  example square) flies near home, never towards 0/0, lands there, and downloads back the same;
* :func:`engage_check`: in a recorded flight the vehicle is first reported in OFFBOARD only in
  the air at the take-off height above home;
* :func:`probe_offboard_loss`: ``companion run`` killed in the air in OFFBOARD: PX4's
  offboard-loss failsafe (``COM_OF_LOSS_T``, ``COM_OBL_RC_ACT``, set as the README's PX4 table
  says) takes over and lands in place;
* :func:`probe_landing_rearm`: after a landing in OFFBOARD (PX4 disarms and keeps the mode) the
  service takes off again.

:class:`~companion.sim.px4_world.FlightTimeline` records the flights.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig, LinkConfig
from companion.errors import CommandError, LinkError
from companion.mavlink.link import MavlinkLink
from companion.px4 import FlightMode, set_mode_params
from companion.service.mission_runner import min_engage_height_m
from companion.sim.px4_sitl import Px4Sitl
from companion.sim.px4_world import FlightEvent, FlightTimeline

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SQUARE_MISSION = REPO / "config" / "missions" / "square.yaml"
#: Arming attempts, a second apart, while PX4 clears a health failure.
ARM_ATTEMPTS = 15
#: PX4 reports mode changes in its 1 Hz heartbeat: a change is seen up to this late.
HEARTBEAT_LAG_S = 1.2
#: PX4's offboard-loss parameters as the README's PX4 table requires them: 0.5 s for a 30 Hz
#: stream, and Land (4). PX4's default, 0 (Position mode), cannot run without RC: PX4 falls
#: back to its emergency flight task ("Matching flight task was not able to run") and drifted
#: up to 1.06 m while descending in SITL.
OFFBOARD_LOSS_PX4_PARAMS: dict[str, float | int] = {"COM_OF_LOSS_T": 0.5, "COM_OBL_RC_ACT": 4}


@dataclass
class ProbeResult:
    """One scenario's verdict, what was measured, and PX4's log lines that show why."""

    name: str
    passed: bool
    detail: str
    figures: dict[str, Any] = field(default_factory=dict)
    px4_log: list[str] = field(default_factory=list)


#: PX4 console lines worth quoting in a verdict.
PX4_EVENT_PATTERN = (r"WARN|ERROR|[Ff]ailsafe|[Aa]rm|[Dd]isarm|[Ll]and|[Tt]akeoff|[Oo]ffboard|far away|"
                     r"[Mm]ission|[Pp]osition mode|Hold|denied")


def engage_check(events: list[FlightEvent], altitude_m: float, tolerance_m: float = 0.05,
                 path: list[tuple[float, float, float, float]] | None = None,
                 requests_s: list[float] | None = None) -> tuple[bool, str]:
    """Whether the vehicle was first reported armed in OFFBOARD while in the air, clear of the
    floor by the service's engage height for a take-off to ``altitude_m`` less ``tolerance_m``
    (:func:`~companion.service.mission_runner.min_engage_height_m`: PX4's take-off aims at its
    home, which can sit tens of centimetres off the floor, and the service climbs the rest in
    OFFBOARD; False also when it never was engaged). OFFBOARD
    while disarmed (PX4 keeps the mode a landing left) is not an engagement. PX4 reports modes
    in its 1 Hz heartbeat, so with the flight's ``path`` ((t_s, x, y, z) samples) the lowest
    height between the heartbeat before that report (at most :data:`HEARTBEAT_LAG_S` before
    it) and the report counts: the engagement happened somewhere in there. ``requests_s``
    (monotonic seconds the service asked for OFFBOARD) narrows that to after the last request
    before the report: PX4 cannot switch before it is asked."""
    first = next((e for e in events if e.mode == "OFFBOARD" and e.armed), None)
    if first is None:
        return False, "never armed in OFFBOARD"
    z = None if first.xyz_map_m is None else first.xyz_map_m[2]
    since_s = first.t_s - HEARTBEAT_LAG_S
    if first.after_t_s is not None:
        since_s = max(since_s, first.after_t_s)
    asked_s = [t for t in requests_s or () if t <= first.t_s]
    if asked_s:
        since_s = max(since_s, asked_s[-1])
    window = [p[3] for p in path or () if since_s <= p[0] <= first.t_s]
    if z is not None and window:
        z = min(z, *window)
    where = "unknown height" if z is None else f"{z:.2f} m above the floor"
    if window:
        where = f"lowest {where} in the {first.t_s - since_s:.1f} s before the report"
    if first.height_above_home_m is not None:
        where += f" ({first.height_above_home_m:.2f} m above home at the report)"
    need = min_engage_height_m(altitude_m)
    ok = first.landed == "IN_AIR" and first.armed and z is not None and z >= need - tolerance_m
    return ok, (f"first OFFBOARD {'armed' if first.armed else 'disarmed'}, {first.landed}, {where} "
                f"(take-off height {altitude_m:.2f} m, engage height {need:.2f} m)")


def _companion(*args: str, timeout_s: float, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s, check=False, env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})})


async def probe_mission_start(sitl: Px4Sitl, mission: Path = SQUARE_MISSION, timeout_s: float = 120.0,
                              max_range_m: float = 6.0) -> ProbeResult:
    """``companion mission upload --start MISSION`` (the CLI, on PX4's GCS link), then watch on
    the onboard link: never farther than ``max_range_m`` from home, lands within 1 m of it
    and disarms; then ``companion mission download`` gives the same steps back."""
    name = "mission_start"
    offset = len(sitl.log_text())
    up = await asyncio.to_thread(_companion, "mission", "upload", str(mission), "--start", "--url", sitl.gcs_url,
                                 "--timeout", "30", timeout_s=90.0)
    if up.returncode != 0:
        return ProbeResult(name, False, f"upload --start failed (exit {up.returncode}): {up.stderr.strip()[-400:]}",
                           px4_log=sitl.log_lines_since(offset, PX4_EVENT_PATTERN))
    tl = FlightTimeline()
    async with MavlinkLink.from_config(LinkConfig(url=sitl.onboard_url)) as link:
        tl.attach(link)
        try:
            await tl.wait_for(lambda t: t.xyz_map_m is not None, 15.0, "a position above home")
            await tl.wait_for(lambda t: t.armed and t.in_air, 30.0, "the take-off")
            await tl.wait_for(lambda t: not t.armed, timeout_s, "the landing and disarm")
        except LinkError as exc:
            detail = str(exc)
        else:
            detail = ""
    lines = sitl.log_lines_since(offset, PX4_EVENT_PATTERN)
    home_xy = _home_xy(tl)
    reach = tl.max_distance_from_m(home_xy)
    final = tl.path[-1][1:] if tl.path else (math.nan,) * 3
    final_m = math.hypot(final[0] - home_xy[0], final[1] - home_xy[1])
    top = max((p[3] for p in tl.path), default=math.nan)
    far = [ln for ln in lines if "far away" in ln]
    down = await asyncio.to_thread(_companion, "mission", "download", str(Path(tempfile.mkdtemp()) / "back.yaml"),
                                   "--url", sitl.gcs_url, "--timeout", "30", timeout_s=90.0)
    same = down.returncode == 0 and f"{_count_steps(mission)} steps" in down.stdout
    ok = not detail and not far and reach <= max_range_m and final_m <= 1.0 and same
    if not detail:
        detail = (f"farthest {reach:.2f} m from home, highest {top:.2f} m, landed {final_m:.2f} m from home"
                  + ("" if same else f"; download differs: {down.stdout.strip() or down.stderr.strip()[-200:]}"))
    return ProbeResult(name, ok, detail, {"max_distance_from_home_m": round(reach, 2),
                                          "landed_from_home_m": round(final_m, 2), "max_height_m": round(top, 2)},
                       lines[-25:])


def _home_xy(tl: FlightTimeline) -> tuple[float, float]:
    # Home is where the vehicle stood armed before the take-off: the first path point.
    return (tl.path[0][1], tl.path[0][2]) if tl.path else (0.0, 0.0)


def _count_steps(mission: Path) -> int:
    data = yaml.safe_load(mission.read_text(encoding="utf-8"))
    return len(data["waypoints"])


async def probe_offboard_loss(sitl: Px4Sitl, cfg: CompanionConfig, workdir: Path,
                              in_offboard_s: float = 3.0, timeout_s: float = 150.0,
                              px4_params: Mapping[str, float | int] | None = None) -> ProbeResult:
    """With PX4's ``px4_params`` set (default :data:`OFFBOARD_LOSS_PX4_PARAMS`), from HOLD on
    the ground, ``companion run --fly-mission`` (simulated camera, PX4's link) flies the demo crossing;
    once PX4 reports OFFBOARD in the air for ``in_offboard_s`` the companion (its whole process
    group) is killed. PX4 must leave OFFBOARD within ``COM_OF_LOSS_T`` (plus the heartbeat's
    lag), stay within 1 m of where the setpoints stopped, land and disarm."""
    from companion.sim.demo_e2e import crossing_waypoints_room, feasible_seed
    from companion.sim.demo_flight import upload_crossing
    from companion.sim.px4_world import Px4World, vehicle_start_map_xy

    name = "offboard_loss"
    for param, value in (OFFBOARD_LOSS_PX4_PARAMS if px4_params is None else px4_params).items():
        await asyncio.to_thread(sitl.param_set, param, value)
    loss_t = sitl.param_get("COM_OF_LOSS_T")
    action = sitl.param_get("COM_OBL_RC_ACT")
    cfg = await asyncio.to_thread(feasible_seed, cfg)
    link_cfg = cfg.link.model_copy(update={"url": sitl.onboard_url})
    world = Px4World(cfg, await vehicle_start_map_xy(link_cfg))
    wps_room = await asyncio.to_thread(crossing_waypoints_room, world.placement, cfg)
    await upload_crossing(sitl.gcs_url, [world.placement.room_to_map_xy(w) for w in wps_room],
                          cfg.planner.flight_altitude_m, connect_timeout_s=30.0)
    await hold_on_ground(sitl)
    conf = workdir / "offboard-loss.yaml"
    conf.write_text(yaml.safe_dump({
        "sim": {"autopilot": "external", "seed": cfg.sim.seed}, "link": {"url": sitl.onboard_url},
        "mqtt": {"enabled": False}, "detector": {"kind": "oracle"},
        "service": {"output_dir": str(workdir / "run"), "map_dir": str(workdir / "run" / "map")}}), encoding="utf-8")
    offset = len(sitl.log_text())
    proc = await asyncio.to_thread(_start_companion_run, conf, workdir / "companion-run.log")
    tl = FlightTimeline()
    figures: dict[str, Any] = {"COM_OF_LOSS_T_s": loss_t, "COM_OBL_RC_ACT": action}
    detail = ""
    try:
        async with MavlinkLink.from_config(LinkConfig(url=sitl.gcs_url)) as link:
            tl.attach(link)
            try:
                await tl.wait_for(lambda t: t.mode == "OFFBOARD" and t.in_air, 90.0, "OFFBOARD in the air")
                await asyncio.sleep(in_offboard_s)
                if tl.mode != "OFFBOARD":
                    raise LinkError(f"the companion left OFFBOARD by itself ({tl.mode}) before the kill")
            except LinkError as exc:
                detail = str(exc)
            finally:
                _kill_group(proc)
            if not detail:
                t_kill = time.monotonic()
                where = tl.xyz_map_m or (math.nan,) * 3
                try:
                    await tl.wait_for(lambda t: t.mode != "OFFBOARD", loss_t + HEARTBEAT_LAG_S + 1.0,
                                      "PX4 to leave OFFBOARD")
                    figures["left_offboard_after_s"] = round(time.monotonic() - t_kill, 2)
                    figures["failsafe_mode"] = tl.mode
                    await tl.wait_for(lambda t: not t.armed, timeout_s, "PX4 to land and disarm")
                except LinkError as exc:
                    detail = str(exc)
                after = [p for p in tl.path if p[0] >= t_kill]
                drift = max((math.hypot(p[1] - where[0], p[2] - where[1]) for p in after), default=math.nan)
                figures["drift_m"] = round(drift, 2)
                if not detail:
                    detail = (f"killed in OFFBOARD at {where[2]:.2f} m; PX4 went to {figures['failsafe_mode']} after "
                              f"{figures['left_offboard_after_s']} s, drifted {drift:.2f} m, landed and disarmed")
                    if not drift <= 1.0:
                        detail += " (drift over 1 m)"
    finally:
        _kill_group(proc)
    lines = sitl.log_lines_since(offset, PX4_EVENT_PATTERN)
    ok = "left_offboard_after_s" in figures and not tl.armed and figures.get("drift_m", math.inf) <= 1.0 \
        and "timed out" not in detail and "before the kill" not in detail
    return ProbeResult(name, ok, detail, figures, lines[-25:])


async def hold_on_ground(sitl: Px4Sitl) -> None:
    """Put the landed vehicle in HOLD (as a pilot leaves it): a vehicle left in MISSION mode
    starts flying the uploaded mission by itself as soon as anyone arms it."""
    from companion.mavsdk_client import MavsdkClient

    async with MavsdkClient(sitl.gcs_url, connect_timeout_s=30.0) as client:
        await client.action.hold()


def _start_companion_run(conf: Path, log_path: Path) -> subprocess.Popen[bytes]:
    """``companion run --fly-mission`` in its own session (so a kill takes its children too)."""
    with log_path.open("w") as out:
        return subprocess.Popen([sys.executable, "-m", "companion", "run", "--fly-mission", "--config", str(conf)],
                                cwd=REPO, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(REPO)})


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10.0)


async def land_in_offboard(sitl: Px4Sitl, altitude_m: float = 1.0, timeout_s: float = 60.0) -> str:
    """Take off (MAVSDK, GCS link), switch to OFFBOARD with raw setpoints at 20 Hz on the
    onboard link and descend to a setpoint under the floor until PX4 detects the landing and
    disarms; returns the mode PX4 reports then (it keeps OFFBOARD)."""
    from companion.mavsdk_client import MavsdkClient

    tl = FlightTimeline()
    async with MavlinkLink.from_config(LinkConfig(url=sitl.onboard_url)) as link:
        tl.attach(link)
        await tl.wait_for(lambda t: t.ned_m is not None, 15.0, "a local position")
        async with MavsdkClient(sitl.gcs_url, connect_timeout_s=30.0) as client:
            # Position mode (where PX4's offboard-loss failsafe lands) does not arm without RC.
            await client.action.hold()
            await client.action.set_takeoff_altitude(altitude_m)
            # After a companion left, PX4 refuses to arm ("Connection to mission computer
            # lost") until our link's heartbeat has been seen for a moment.
            for attempt in range(ARM_ATTEMPTS):
                try:
                    await client.arm()
                    break
                except CommandError:
                    if attempt == ARM_ATTEMPTS - 1:
                        raise
                    await asyncio.sleep(1.0)
            await client.action.takeoff()
        await tl.wait_for(lambda t: t.mode == "HOLD" and t.in_air, timeout_s, f"the take-off to {altitude_m:.1f} m")
        assert tl.ned_m is not None
        target = list(tl.ned_m)

        descend = [False]

        async def stream() -> None:
            position_only, velocity_only = 0b0000_1111_1111_1000, 0b0000_1111_1100_0111
            while True:
                if descend[0]:
                    # Down at 0.7 m/s: PX4's land detector needs a descending velocity setpoint.
                    msg = link.mav.set_position_target_local_ned_encode(
                        link.time_boot_ms(), 1, 1, mavlink.MAV_FRAME_LOCAL_NED, velocity_only, 0, 0, 0,
                        0, 0, 0.7, 0, 0, 0, 0, 0)
                else:
                    msg = link.mav.set_position_target_local_ned_encode(
                        link.time_boot_ms(), 1, 1, mavlink.MAV_FRAME_LOCAL_NED, position_only, *target,
                        0, 0, 0, 0, 0, 0, 0, 0)
                link.send(msg)
                await asyncio.sleep(0.05)

        task = asyncio.create_task(stream())
        try:
            await asyncio.sleep(1.0)
            p1, p2, p3 = set_mode_params(FlightMode.OFFBOARD)
            link.send(link.mav.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, p1, p2, p3, 0, 0, 0, 0))
            await tl.wait_for(lambda t: t.mode == "OFFBOARD", 10.0, "OFFBOARD")
            descend[0] = True
            await tl.wait_for(lambda t: not t.armed, timeout_s, "the landing and disarm in OFFBOARD")
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await asyncio.sleep(HEARTBEAT_LAG_S)
        return tl.mode


async def probe_landing_rearm(sitl: Px4Sitl, cfg: CompanionConfig, out_dir: Path,
                              timeout_s: float = 240.0) -> tuple[ProbeResult, Any]:
    """Land in OFFBOARD (:func:`land_in_offboard`), then fly the demo with the service: it must
    arm and take off again. Returns the verdict and the flight (a :class:`Px4Flight`)."""
    from companion.sim.demo_px4 import fly_px4

    name = "landing_rearm"
    offset = len(sitl.log_text())
    try:
        mode = await land_in_offboard(sitl)
    except (LinkError, TimeoutError, Exception) as exc:  # noqa: BLE001 - MAVSDK raises its own errors
        return ProbeResult(name, False, f"could not land in OFFBOARD first: {exc!r}",
                           px4_log=sitl.log_lines_since(offset, PX4_EVENT_PATTERN)), None
    await asyncio.sleep(1.5)
    flight = await fly_px4(cfg, out_dir, sitl=sitl, use_broker=False, timeout_s=timeout_s)
    events = flight.timeline.events
    took_off = any(e.armed and e.landed == "IN_AIR" for e in events)
    lines = sitl.log_lines_since(offset, PX4_EVENT_PATTERN)
    err = flight.summary.get("mission_error")
    detail = (f"landed in {mode}, disarmed; the service then {'took off again' if took_off else 'did not take off'}"
              + (f" ({err})" if err and not took_off else ""))
    return ProbeResult(name, took_off, detail, {"mode_after_landing": mode, "modes": flight.summary["modes"]},
                       lines[-25:]), flight
