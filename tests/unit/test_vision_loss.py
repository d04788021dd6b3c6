"""When PX4's only position source, the SLAM pose, stops: hold, resume, land (companion.service.vision_loss)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig
from companion.mavlink.link import MavlinkLink
from companion.mavlink.params import ParamWatch
from companion.mavlink.vision import VisionPose, VisionStream
from companion.px4 import MAV_PARAM_TYPE_INT32, FlightMode, encode_param_value
from companion.service.app import CompanionService
from companion.service.position_source import ServiceLocalization
from companion.service.vision_loss import (
    FLOW_ASKS,
    FLOW_PARAM,
    LAND_MARGIN_S,
    PARAM_RETRY_S,
    EstimateLimits,
    VisionLossAction,
    VisionLossGuard,
    VisionLossMonitor,
    check_land_after,
)
from semmap.errors import ConfigError

HOLD, RESUME, LAND = VisionLossAction.HOLD, VisionLossAction.RESUME, VisionLossAction.LAND


def _run(monitor: VisionLossMonitor, last_sent: list[float | None], until_s: float,
         in_air: bool = True) -> list[tuple[float, VisionLossAction]]:
    """Step every 0.1 s; ``last_sent`` the times vision went out (None: never)."""
    out = []
    for k in range(int(until_s * 10) + 1):
        now = 0.1 * k
        sent = [t for t in last_sent if t is not None and t <= now + 1e-9]
        age = now - sent[-1] if sent else None
        action = monitor.step(now, age, in_air)
        if action is not None:
            out.append((round(now, 1), action))
    return out


def test_a_three_second_loss_holds_then_resumes() -> None:
    m = VisionLossMonitor(hold_after_s=1.0, land_after_s=4.0)
    sent = [0.1 * k for k in range(0, 21)] + [0.1 * k for k in range(50, 80)]  # nothing from 2.0 to 5.0 s
    assert _run(m, sent, 7.9) == [(3.0, HOLD), (5.0, RESUME)]
    assert m.pose_ok


def test_a_long_loss_lands_once() -> None:
    m = VisionLossMonitor(hold_after_s=1.0, land_after_s=4.0)
    assert _run(m, [0.0, 0.5], 10.0) == [(1.5, HOLD), (4.5, LAND)]
    assert not m.pose_ok  # the planner's setpoints are not flown while landing


def test_vision_coming_back_during_the_landing_does_not_take_off_again() -> None:
    m = VisionLossMonitor(hold_after_s=1.0, land_after_s=4.0)
    assert _run(m, [0.0, 6.0, 6.1, 6.2], 7.0) == [(1.0, HOLD), (4.0, LAND)]


def test_on_the_ground_nothing_happens_and_a_landing_ends() -> None:
    m = VisionLossMonitor(hold_after_s=1.0, land_after_s=4.0)
    assert _run(m, [None], 10.0, in_air=False) == []
    _run(m, [0.0], 5.0)
    assert m.state is LAND
    assert m.step(6.0, 6.0, in_air=False) is None and m.pose_ok


def test_never_any_vision_in_the_air_counts_from_the_first_look() -> None:
    m = VisionLossMonitor(hold_after_s=1.0, land_after_s=4.0)
    assert m.step(10.0, None, True) is None
    assert m.step(11.0, None, True) is HOLD
    assert m.step(14.0, None, True) is LAND


def test_hold_must_come_before_land() -> None:
    with pytest.raises(ConfigError, match="vision_lost_land_s"):
        VisionLossMonitor(hold_after_s=4.0, land_after_s=4.0)


def test_the_guard_tells_the_ground_station_and_lands() -> None:
    link = MavlinkLink("udpout://127.0.0.1:9")
    sent: list[mavlink.MAVLink_message] = []
    link.send = sent.append  # type: ignore[method-assign]
    now = [0.0]
    landed: list[bool] = []

    async def land() -> None:
        landed.append(True)

    guard = VisionLossGuard(VisionLossMonitor(1.0, 4.0), link, lambda: now[0], lambda: True, land,
                            clock=lambda: now[0])

    async def main() -> list[VisionLossAction | None]:
        out = []
        for t in (0.5, 1.2, 3.0, 4.1, 5.0):
            now[0] = t
            out.append(await guard.check())
        return out

    assert asyncio.run(main()) == [None, HOLD, None, LAND, None]
    assert landed == [True]
    texts = [m.text for m in sent if m.get_type() == "STATUSTEXT"]
    assert texts[0].startswith("SLAM lost: holding") and texts[1].startswith("SLAM lost 4s: landing")
    assert [m.severity for m in sent] == [mavlink.MAV_SEVERITY_WARNING, mavlink.MAV_SEVERITY_CRITICAL]


#: PX4's defaults: EKF2_NOAID_TOUT 5 s (in microseconds), MPC_LAND_SPEED 0.7 m/s.
PX4_DEFAULTS = EstimateLimits.from_params({"EKF2_NOAID_TOUT": 5_000_000, "MPC_LAND_SPEED": 0.7})


def test_the_landing_is_timed_to_touch_down_before_px4_drops_its_position() -> None:
    assert PX4_DEFAULTS.noaid_timeout_s == pytest.approx(5.0)
    # From 1.4 m: 2 s of descent and the margin before PX4's 5 s.
    assert LAND_MARGIN_S == 1.0
    assert PX4_DEFAULTS.land_deadline_s(1.4) == pytest.approx(5.0 - 2.0 - LAND_MARGIN_S)
    m = VisionLossMonitor(1.0, limits=PX4_DEFAULTS, default_height_m=1.4)
    assert m.deadline_s(1.4) == m.deadline_s(None) == pytest.approx(2.0)
    assert _run(m, [0.0], 3.0) == [(1.0, HOLD), (2.0, LAND)]
    # A configured time later than that is capped by it (a mission item's altitude above the
    # flight altitude), an earlier one kept.
    assert VisionLossMonitor(1.0, 3.5, limits=PX4_DEFAULTS).deadline_s(1.4) == pytest.approx(2.0)
    assert VisionLossMonitor(1.0, 1.5, limits=PX4_DEFAULTS).deadline_s(1.4) == pytest.approx(1.5)


def test_too_high_for_a_hold_the_vehicle_lands_at_once() -> None:
    m = VisionLossMonitor(1.0, limits=PX4_DEFAULTS)
    steps = []
    for k in range(30):
        action = m.step(0.1 * k, 0.1 * k, True, height_m=2.8)  # 4 s of descent: no time to hold
        if action is not None:
            steps.append((round(0.1 * k, 1), action))
    assert steps == [(1.0, LAND)]


def test_before_px4_has_answered_the_loss_lands_at_the_hold() -> None:
    assert VisionLossMonitor(1.0).deadline_s(1.0) == 1.0
    assert VisionLossMonitor(1.0, 4.0).deadline_s(1.0) == 4.0  # a configured time stands alone


def test_a_landing_time_px4_cannot_carry_is_refused_with_what_to_change() -> None:
    with pytest.raises(ConfigError, match=r"vision_lost_land_s \(4 s\).*flight_altitude_m \(1\.5 m\).*"
                                          r"MPC_LAND_SPEED.*by 1\.86 s.*EKF2_NOAID_TOUT"):
        check_land_after(4.0, 1.0, PX4_DEFAULTS, 1.5)
    assert check_land_after(1.8, 1.0, PX4_DEFAULTS, 1.5) == pytest.approx(5.0 - 1.0 - 1.5 / 0.7)
    assert check_land_after(None, 1.0, PX4_DEFAULTS, 1.5) == pytest.approx(5.0 - 1.0 - 1.5 / 0.7)
    with pytest.raises(ConfigError, match="MPC_LAND_SPEED"):
        EstimateLimits.from_params({"EKF2_NOAID_TOUT": 5_000_000, "MPC_LAND_SPEED": 0.0})


def test_the_time_without_vision_counts_from_the_last_poses_capture() -> None:
    # EKF2's timeout runs from the fused pose's stamp (its capture), not from when we sent it.
    base = CompanionConfig()
    cfg = base.model_copy(update={"service": base.service.model_copy(update={"localization": "slam"}),
                                  "link": base.link.model_copy(update={"external_vision": True})})
    loc = ServiceLocalization(cfg)
    link = MavlinkLink("udpout://127.0.0.1:9")
    link.send = lambda msg: None  # type: ignore[method-assign]
    captured = time.monotonic() - 0.3
    loc.stream = VisionStream(link, lambda: VisionPose(captured, np.eye(4), position_std_m=0.05))
    assert loc.vision_age_s() is None
    assert loc.stream.send_once()
    age = loc.vision_age_s()
    assert age is not None and 0.3 <= age < 0.4


class _FakeVehicle:
    """What CompanionService.deactivate touches: an offboard stream and the landed state."""

    def __init__(self) -> None:
        self.released: list[object] = []
        self.offboard = self
        self.state = self
        self.streams = True

    async def release(self, then: object) -> None:
        self.released.append(then)
        self.streams = False

    async def wait_for(self, *args: object) -> None:
        return None

    def snapshot(self) -> object:
        return type("Snapshot", (), {"in_air": False})()


def test_a_stop_while_the_slam_lost_landing_is_commanded_keeps_the_landing(tmp_path: Path) -> None:
    # The landing ends the mission, and a mission's end can stop the service at once: its
    # hand-over (on_sigterm: hold) must not turn PX4's Land back into a Hold without a position.
    svc = CompanionService(CompanionConfig(), cast(Any, None), out_dir=tmp_path)
    assert svc.cfg.service.on_sigterm == "hold"
    vehicle = _FakeVehicle()
    svc.vehicle = cast(Any, vehicle)
    asyncio.run(svc.missions.land_here("the SLAM pose (PX4's position source) is lost"))
    asyncio.run(svc.deactivate())
    assert vehicle.released == [FlightMode.LAND]


def _param_value(link: MavlinkLink, name: str, value: int) -> mavlink.MAVLink_message:
    msg = link.mav.param_value_encode(name.encode("ascii"), encode_param_value(value, MAV_PARAM_TYPE_INT32),
                                      MAV_PARAM_TYPE_INT32, 1, 0)
    msg._header.srcSystem, msg._header.srcComponent = 1, 1  # as PX4 sends it
    return msg


@pytest.mark.parametrize(("of_ctrl", "warned"), [(0, True), (1, False)])
def test_the_guard_warns_when_px4_has_no_flow_sensor_to_hold_on(of_ctrl: int, warned: bool,
                                                                  caplog: pytest.LogCaptureFixture) -> None:
    """Without optical flow a hold drifts on PX4's IMU alone (PX4 SITL: into a chair's clearance)."""
    link = MavlinkLink("udpout://127.0.0.1:9")
    sent: list[mavlink.MAVLink_message] = []
    link.send = sent.append  # type: ignore[method-assign]
    now = [0.0]

    async def land() -> None:
        return None

    flow = ParamWatch(link, 1, 1, (FLOW_PARAM,))
    guard = VisionLossGuard(VisionLossMonitor(1.0, 4.0), link, lambda: None, lambda: False, land,
                            clock=lambda: now[0], period_s=0.01, flow_param=flow)

    async def main() -> None:
        task = asyncio.create_task(guard.run())
        for _ in range(5):  # 5 retry periods without an answer: asked FLOW_ASKS times, no more
            await asyncio.sleep(0.03)
            now[0] += PARAM_RETRY_S
        flow._on_param(_param_value(link, FLOW_PARAM, of_ctrl))
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    with caplog.at_level(logging.WARNING, logger="companion.service.vision_loss"):
        asyncio.run(main())
    asks = [m for m in sent if m.get_type() == "PARAM_REQUEST_READ"]
    assert len(asks) == FLOW_ASKS
    assert guard.flow_aided is (not warned)
    assert any("fuses no optical flow (EKF2_OF_CTRL 0)" in r.getMessage() for r in caplog.records) is warned
