"""PX4 SITL without GPS takes the companion's ODOMETRY as its position: EKF2 fuses our frames,
covariances and timestamps, follows a reset_counter bump, and its estimate is SIH's truth.

The pose sent here is SIH's own truth (HIL_STATE_QUATERNION on the display link) through the
companion's VisionStream, so what is tested is the interface to EKF2, not the SLAM;
bench/px4_gps_denied.py flies the SLAM pose."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import time
from collections.abc import Iterator

import numpy as np
import pytest

from companion.config import CompanionConfig, LinkConfig
from companion.errors import CommandError
from companion.geo import GeoOrigin
from companion.mavlink.timesync import TimesyncConvergence
from companion.mavlink.vehicle import Vehicle
from companion.mavlink.vision import ECHOED_HEIGHT_STD_M, VisionPose, VisionStream
from companion.sim.flow_sensor import FLOW_PX4_PARAMS, FlowSensorModel
from companion.sim.px4_gps_denied import (
    EstimateRecorder,
    GpsDeniedSitl,
    SihTruth,
    placement_around_start,
)
from companion.sim.px4_sitl import sitl_available
from companion.sim.sim_world import SharedSimState

pytestmark = [pytest.mark.px4, pytest.mark.slow]

#: The poses go out stamped this long before they arrived here.
AGE_S = 0.1
#: PX4 maps our stamps onto its clock this soon after the stream starts (s).
MAPPED_WITHIN_S = 20.0
#: The take-off climbs this high above home (m), and is watched this long (s) after arming.
TAKEOFF_ALT_M = 1.0
TAKEOFF_WATCH_S = 12.0
#: How late a MAVLink message may be handled after it arrived on a loaded machine (s).
ARRIVAL_JITTER_S = 0.1


@pytest.fixture
def gps_denied_sitl(request: pytest.FixtureRequest) -> Iterator[GpsDeniedSitl]:
    """A fresh PX4 for each test (parameters added by indirect parametrization): the take-off
    test needs a vehicle whose estimator has not been moved by another test's vision resets."""
    ok, why = sitl_available()
    if not ok:
        pytest.skip(why)
    with GpsDeniedSitl(params=getattr(request, "param", None)) as running:
        yield running


def _age_us(odom: str) -> int:
    """How much older than its receipt PX4 took a vehicle_visual_odometry sample to be."""
    m = re.search(r"timestamp_sample: \d+ \((\d+) us before timestamp\)", odom)
    assert m is not None, odom
    return int(m.group(1))


def _field(text: str, name: str) -> list[float]:
    m = re.search(rf"^\s*{name}: \[([^\]]*)\]", text, re.M)
    assert m is not None, f"no {name} in {text!r}"
    return [float(v) for v in m.group(1).split(",")]


def test_ekf2_takes_the_companions_odometry_as_its_position(gps_denied_sitl: GpsDeniedSitl) -> None:
    sitl = gps_denied_sitl
    out: dict[str, object] = {}

    async def run() -> None:
        truth = SihTruth(sitl.display_url, placement_around_start(CompanionConfig()), SharedSimState())
        offset = np.zeros(3)
        reset = [0]

        def source() -> VisionPose | None:
            if truth.latest is None:
                return None
            stamp, T = truth.latest
            T = T.copy()
            T[:3, 3] += offset
            # Stamped AGE_S before it arrived (the vehicle stands still): PX4 must fuse it that old.
            return VisionPose(stamp - AGE_S, T, 100, reset[0], 0.05, math.radians(2.0))

        async with truth, Vehicle(LinkConfig(url=sitl.onboard_url)) as v:
            await asyncio.to_thread(sitl.stream_truth)
            await truth.wait_first()
            async with VisionStream(v.link, source, 30.0):
                # PX4 maps our stamps onto its clock once its TIMESYNC estimate has converged
                # (500 answers); until then it stamps the pose on arrival.
                conv = TimesyncConvergence(v.link, v.commands.sender)
                detach = conv.attach()
                converging = asyncio.create_task(conv.run())
                t0 = time.monotonic()
                while time.monotonic() - t0 < MAPPED_WITHIN_S:
                    await asyncio.sleep(1.0)
                    out["age_us"] = _age_us(await asyncio.to_thread(sitl.listener, "vehicle_visual_odometry"))
                    if abs(out["age_us"] - AGE_S * 1e6) < 50_000:  # type: ignore[operator]
                        out["mapped_after_s"] = time.monotonic() - t0
                        break
                await asyncio.to_thread(sitl.wait_ready)  # no GPS: ready only on our vision
                out["age_us"] = _age_us(await asyncio.to_thread(sitl.listener, "vehicle_visual_odometry"))
                await converging
                detach()
                rtts = sorted(r for _, _, r in v.autopilot_clock._samples)
                out["rtt_ms_p10_p50"] = [round(1e3 * rtts[len(rtts) // 10], 1), round(1e3 * rtts[len(rtts) // 2], 1)]
                out["hz"] = (await asyncio.to_thread(sitl.uorb_top_hz, ["vehicle_visual_odometry"]))[
                    "vehicle_visual_odometry"]
                out["odom"] = await asyncio.to_thread(sitl.listener, "vehicle_visual_odometry")
                out["flags"] = await asyncio.to_thread(sitl.listener, "estimator_status_flags")
                out["ev_pos"] = await asyncio.to_thread(sitl.listener, "estimator_aid_src_ev_pos")
                s = v.snapshot()
                assert s.position_ned_m is not None and truth.latest is not None
                t = truth.latest[1][:3, 3]
                out["err_m"] = math.hypot(s.position_ned_m[0] - t[1], s.position_ned_m[1] - t[0])
                # The pose jumps 0.5 m east with the reset counter bumped: EKF2 moves to it at once.
                offset[0], reset[0] = 0.5, 1
                t0 = time.monotonic()
                while time.monotonic() - t0 < 3.0:
                    await asyncio.sleep(0.1)
                    s = v.snapshot()
                    assert s.position_ned_m is not None
                    if abs(s.position_ned_m[1] - (truth.latest[1][0, 3] + 0.5)) < 0.05:
                        out["reset_after_s"] = time.monotonic() - t0
                        break

    asyncio.run(run())
    odom, flags = str(out["odom"]), str(out["flags"])
    assert float(out["hz"]) >= 20.0, out["hz"]  # type: ignore[arg-type]
    # Our covariance reached EKF2 as we sent it: x/y 0.05 m, yaw 2 deg, the echoed height wide.
    var = _field(odom, "position_variance")
    assert var == pytest.approx([0.0025, 0.0025, ECHOED_HEIGHT_STD_M ** 2], rel=1e-3), odom
    assert _field(odom, "orientation_variance")[2] == pytest.approx(math.radians(2.0) ** 2, rel=1e-2), odom
    # ... and EKF2 fuses it (all three finite), not EKF2_EVP_NOISE (0.02 m: 0.0004).
    fused = _field(str(out["ev_pos"]), "observation_variance")
    assert fused[:2] == pytest.approx([0.0025, 0.0025], rel=1e-2), out["ev_pos"]
    # Stamped at capture on PX4's clock (TIMESYNC), not on arrival: fused as old as it was,
    # seconds after the stream started (PX4's default TIMESYNC rate takes 50 s).
    assert "mapped_after_s" in out, out
    assert abs(float(out["age_us"]) - AGE_S * 1e6) < 50_000, out  # type: ignore[arg-type]
    assert "cs_ev_pos: True" in flags and "cs_ev_yaw: True" in flags and "cs_gnss_pos: False" in flags, flags
    assert float(out["err_m"]) < 0.05, out  # type: ignore[arg-type]
    assert "reset_after_s" in out and float(out["reset_after_s"]) < 1.5, out  # type: ignore[arg-type]


@pytest.mark.parametrize("gps_denied_sitl", [FLOW_PX4_PARAMS], indirect=True)
def test_the_height_estimate_follows_the_vehicle_through_take_off(gps_denied_sitl: GpsDeniedSitl) -> None:
    """Vision gives EKF2 no height; from "Takeoff detected" until the vehicle has climbed 0.1 m
    EKF2 has no range finder either (SIH's reads a constant on the floor, which EKF2's stuck
    check holds against it) and no zero-velocity fusion, so the baro must stay fused: with its
    ground-effect dead zone the estimate ran off upwards during the spool-up and the take-off
    controller, following it, left the vehicle on the floor.

    The vehicle carries the simulated flow sensor, as the bench's ``--flow-sensor`` flights
    do: in the air EKF2 must fuse its flow, not reject it (a sign or frame wrong)."""
    sitl = gps_denied_sitl
    truth = SihTruth(sitl.display_url, placement_around_start(CompanionConfig()), SharedSimState(),
                     flow=FlowSensorModel())
    flags: list[str] = []
    est = EstimateRecorder()
    armed_at: list[float] = []

    def source() -> VisionPose | None:
        if truth.latest is None:
            return None
        stamp, T = truth.latest
        return VisionPose(stamp, T, 100, 0, 0.05, math.radians(2.0))

    async def run() -> None:
        async with truth, Vehicle(LinkConfig(url=sitl.onboard_url)) as v:
            detach = est.attach(v.link)
            await asyncio.to_thread(sitl.stream_truth)
            await truth.wait_first()
            async with VisionStream(v.link, source, 30.0):
                await asyncio.to_thread(sitl.wait_ready)
                origin = GeoOrigin(47.397742, 8.545594, 0.0)
                t0 = time.monotonic()
                while v.snapshot().home is None and time.monotonic() - t0 < 30.0:
                    v.link.send(v.link.mav.set_gps_global_origin_encode(
                        1, int(origin.lat_deg * 1e7), int(origin.lon_deg * 1e7), 0, int(time.time() * 1e6)))
                    await asyncio.sleep(3.0)
                assert v.snapshot().home is not None, "PX4 set no home from SET_GPS_GLOBAL_ORIGIN within 30 s"
                t0 = time.monotonic()
                while not v.snapshot().armed:  # PX4 refuses while its position settles on the new origin
                    assert time.monotonic() - t0 < 40.0, "PX4 did not arm within 40 s"
                    with contextlib.suppress(CommandError):
                        await v.commands.arm()
                    await asyncio.sleep(2.0)
                armed_at.append(time.monotonic())
                await v.commands.takeoff(TAKEOFF_ALT_M)
                await asyncio.sleep(TAKEOFF_WATCH_S)
                flags.append(await asyncio.to_thread(sitl.listener, "estimator_status_flags"))
                await v.commands.land()
            detach()

    asyncio.run(run())
    e = np.array(est.rows, dtype=np.float64)
    before = e[(e[:, 0] < armed_at[0]) & (e[:, 0] > armed_at[0] - 2.0)]
    during = e[(e[:, 0] >= armed_at[0]) & (e[:, 0] <= armed_at[0] + TAKEOFF_WATCH_S)]
    assert len(before) > 10 and len(during) > 100, (len(before), len(during))
    # Heights above where each stood: PX4's local z has its own origin.
    z0 = float(np.mean(before[:, 3] - truth.at(before[:, 0], "local")[:, 2]))
    true_z = truth.at(during[:, 0], "local")[:, 2]
    # Estimate and truth are both stamped on arrival, and on a loaded 2-core machine either
    # can wait up to ~0.1 s for this process: at take-off speed (1.5 m/s) that alone reads as
    # 0.15 m. Each estimate is judged against the truth within that jitter of its stamp; an
    # estimate running off while the vehicle is on the floor stays off over the whole window.
    err = np.min([np.abs(during[:, 3] - z0 - truth.at(during[:, 0] + dt, "local")[:, 2])
                  for dt in np.linspace(-ARRIVAL_JITTER_S, ARRIVAL_JITTER_S, 9)], axis=0)
    assert true_z.max() > 0.5 * TAKEOFF_ALT_M, f"the vehicle never climbed: true height at most {true_z.max():.2f} m"
    assert err.max() < 0.15, (f"PX4's height left the truth by {err.max():.2f} m during the take-off "
                              f"(at {during[int(err.argmax()), 0] - armed_at[0]:.1f} s after arming)")
    assert truth.flow_sent > 100
    assert "cs_opt_flow: True" in flags[0], flags[0]
    assert "reject_optflow_x: False" in flags[0] and "reject_optflow_y: False" in flags[0], flags[0]
