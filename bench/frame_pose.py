"""How well a camera frame is posed from the autopilot's telemetry (companion.sources.poses).

The mock autopilot flies a square in OFFBOARD with a 90 deg yaw turn at each corner (the
turns and the accelerations are where interpolation errs). The service's parts run as on
the drone: the :class:`~companion.mavlink.vehicle.Vehicle` link, the
:class:`~companion.sources.poses.TelemetryPoseRecorder` on it, the shared-memory history.
At the camera's rate the true body pose and its instant (``time.monotonic``) are taken from
the mock's latest physics tick, as the simulated camera takes them, and later looked up in the
history as :class:`~companion.sources.poses.TelemetryPosedSource` looks a frame up.

Cases (one process, one after the other):

* ``attitude_100hz``: PX4's onboard-link rates (ATTITUDE 100 Hz, LOCAL_POSITION_NED 30 Hz),
  stamps from ``time_boot_ms`` (:class:`~companion.sources.poses.BootClock`);
* ``attitude_100hz_busy_loop``: the same with the event loop blocked 25 ms every 100 ms (a
  busy service; the mock shares the loop, as in the demo), so messages arrive late;
* ``arrival_stamps_busy_loop``: the busy loop with samples stamped on arrival (what the
  recorder would do without :class:`BootClock`);
* ``attitude_30hz``: ATTITUDE slowed to 30 Hz with ``MAV_CMD_SET_MESSAGE_INTERVAL``.

Figures: position error (mm) and attitude error (deg, the angle of the relative rotation),
p50 / p95 / max, and the fraction of frames that found no pose.

``python bench/frame_pose.py [--quick]``; the last line is a JSON object with the figures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.config import LinkConfig  # noqa: E402
from companion.mavlink.failsafe import PositionSetpoint  # noqa: E402
from companion.mavlink.vehicle import Vehicle  # noqa: E402
from companion.px4 import FlightMode  # noqa: E402
from companion.service.mission_runner import took_off  # noqa: E402
from companion.sim.autopilot import MockAutopilot  # noqa: E402
from companion.sim.autopilot.behaviour import Px4Behaviour  # noqa: E402
from companion.sources.poses import BootClock, SharedPoseHistory, TelemetryPoseRecorder  # noqa: E402

CAMERA_HZ = 15.0
ALT_M = 1.0
SIDE_M = 2.0
#: How long after a frame's instant it is looked up (the camera's read, well inside the history).
LOOKUP_DELAY_S = 0.15


class _ArrivalClock(BootClock):
    """Stamps on arrival: the recorder without the boot-time mapping."""

    def to_local(self, boot_s: float, arrival_s: float) -> float:
        return arrival_s


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d_mm = 1e3 * float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    c = (float(np.trace(T_est[:3, :3].T @ T_true[:3, :3])) - 1.0) / 2.0
    return d_mm, math.degrees(math.acos(max(-1.0, min(1.0, c))))


async def _busy(period_s: float, block_s: float) -> None:
    while True:
        await asyncio.sleep(period_s)
        time.sleep(block_s)  # noqa: ASYNC251 - the point: the loop is held, nothing is received


async def run_case(corners: int, attitude_hz: float | None, busy: bool, arrival: bool) -> dict[str, Any]:
    cfg = LinkConfig(url="udpin://127.0.0.1:0", setpoint_rate_hz=30.0)
    history = SharedPoseHistory()
    truth: list[tuple[float, np.ndarray]] = []
    errs: list[tuple[float, float]] = []
    unposed = 0
    async with Vehicle(cfg) as vehicle:
        port = vehicle.link.transport.local_address[1]  # type: ignore[attr-defined]
        params = {"MPC_TKO_SPEED": 3.0, "COM_DISARM_PRFLT": -1.0}
        # The square's corners are judged against the mock's floor-based truth, so its local
        # origin is put on the floor; every other PX4 way stays on.
        async with MockAutopilot(local_port=0, remote_ports=[port], params=params,
                                 behaviour=Px4Behaviour(floor_z_ned_m=0.0)) as ap:
            recorder = TelemetryPoseRecorder(history, remote_to_local=vehicle.autopilot_clock.to_local,
                                             map_frame=lambda: vehicle.snapshot().map_frame)
            if arrival:
                recorder.boot_clock = _ArrivalClock()
            remove = vehicle.link.add_listener(recorder.handle, recorder.MESSAGES)
            await vehicle.wait_connected(10.0)
            if attitude_hz is not None:
                await vehicle.commands.set_message_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, attitude_hz)
            await vehicle.state.wait_for(lambda s: s.ready_to_arm, 30.0, "the autopilot's pre-flight checks")
            await vehicle.commands.arm()
            await vehicle.commands.takeoff(ALT_M)
            await vehicle.state.wait_for(lambda s: took_off(s, ALT_M), 20.0, "takeoff")

            async def camera() -> None:
                nonlocal unposed
                while True:
                    await asyncio.sleep(1.0 / CAMERA_HZ)
                    truth.append((ap.tick_monotonic_s, ap.poses_map_body()[1]))
                    while truth and truth[0][0] < time.monotonic() - LOOKUP_DELAY_S:
                        t, T_true = truth.pop(0)
                        T = history.pose_at(t, 0.25)
                        if T is None:
                            unposed += 1
                        else:
                            errs.append(_errors(np.asarray(T), np.asarray(T_true)))

            tasks = [asyncio.create_task(camera())]
            if busy:
                tasks.append(asyncio.create_task(_busy(0.1, 0.025)))
            try:
                ctl = vehicle.offboard
                here = vehicle.snapshot().position_ned_m or (0.0, 0.0, -ALT_M)
                ctl.set_setpoint(PositionSetpoint((here[0], here[1], -ALT_M), yaw_rad=0.0))
                await ctl.engage()
                square = [(SIDE_M, 0.0), (SIDE_M, SIDE_M), (0.0, SIDE_M), (0.0, 0.0)]
                for i in range(corners):
                    n, e = square[i % 4]
                    target = (here[0] + n, here[1] + e, -ALT_M)
                    ctl.set_setpoint(PositionSetpoint(target, yaw_rad=math.radians(90.0 * (i % 4))))
                    await ap.wait_until(lambda t=target: math.dist(ap.position_ned_m, t) < 0.1, 30.0, "corner")
                    ctl.set_setpoint(PositionSetpoint(target, yaw_rad=math.radians(90.0 * (i % 4 + 1))))
                    await asyncio.sleep(1.5)  # the turn on the spot
                await ctl.release(FlightMode.HOLD)
            finally:
                for t in tasks:
                    t.cancel()
                remove()
    e = np.array(errs) if errs else np.zeros((0, 2))

    def pct(col: int, q: float) -> float:
        return round(float(np.percentile(e[:, col], q)), 3) if len(e) else float("nan")

    return {"frames": len(errs) + unposed, "unposed_frac": round(unposed / max(1, len(errs) + unposed), 4),
            "position_mm_p50": pct(0, 50), "position_mm_p95": pct(0, 95), "position_mm_max": pct(0, 100),
            "attitude_deg_p50": pct(1, 50), "attitude_deg_p95": pct(1, 95), "attitude_deg_max": pct(1, 100)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="two corners per case instead of four")
    args = ap.parse_args(argv)
    corners = 2 if args.quick else 4
    cases = {
        "attitude_100hz": (None, False, False),
        "attitude_100hz_busy_loop": (None, True, False),
        "arrival_stamps_busy_loop": (None, True, True),
        "attitude_30hz": (30.0, False, False),
    }
    results = {name: asyncio.run(run_case(corners, *spec)) for name, spec in cases.items()}
    cols = ["frames", "unposed_frac", "position_mm_p50", "position_mm_p95", "position_mm_max",
            "attitude_deg_p50", "attitude_deg_p95", "attitude_deg_max"]
    print(f"frames posed from telemetry: a {SIDE_M:.0f} m square at {ALT_M:.0f} m, {corners} corners, "
          f"90 deg turn at each, camera {CAMERA_HZ:.0f} Hz")
    print(f"{'case':<28}" + "".join(f"{c:>18}" for c in cols))
    for name, r in results.items():
        print(f"{name:<28}" + "".join(f"{r[c]:>18}" for c in cols))
    print(json.dumps({"corners": corners, "camera_hz": CAMERA_HZ, **results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
