"""The simulated flow sensor reads as PX4's flow sensors do (PX4 user guide, Optical Flow:
forwards +Y, right -X), and its gyro is what EKF2 takes out again."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig
from companion.sim.flow_sensor import FULL_QUALITY, FlowSensorModel, flow_rad_fields, integration_dt
from companion.sim.px4_gps_denied import SihTruth, placement_around_start
from companion.sim.sim_world import SharedSimState

LEVEL_NORTH = np.eye(3)  # R_ned_frd: level, nose north


def _yawed(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(("v_ned", "expected_xy"), [
    ((1.0, 0.0, 0.0), (0.0, +1.0)),   # forwards: +Y
    ((-1.0, 0.0, 0.0), (0.0, -1.0)),  # backwards: -Y
    ((0.0, 1.0, 0.0), (-1.0, 0.0)),   # right: -X
    ((0.0, -1.0, 0.0), (+1.0, 0.0)),  # left: +X
])
def test_motion_reads_with_px4s_signs(v_ned: tuple[float, float, float], expected_xy: tuple[float, float]) -> None:
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.array(v_ned), LEVEL_NORTH, np.zeros(3), height_m=0.5)
    # 1 m/s at 0.5 m is 2 rad/s, over 20 ms 0.04 rad.
    assert s.flow_xy_rad == pytest.approx((0.04 * expected_xy[0], 0.04 * expected_xy[1]), abs=1e-9)
    assert s.quality == FULL_QUALITY


def test_the_flow_is_in_the_body_frame() -> None:
    """Heading east, a northward motion is to the vehicle's left."""
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.array([1.0, 0.0, 0.0]), _yawed(np.pi / 2), np.zeros(3), 1.0)
    assert s.flow_xy_rad == pytest.approx((0.02, 0.0), abs=1e-9)


def test_a_rotation_in_place_reads_as_its_gyro() -> None:
    """EKF2 subtracts the integrated gyro: what is left of a pure rotation must be nothing."""
    rates = np.array([0.3, -0.2, 0.1])
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.zeros(3), LEVEL_NORTH, rates, 0.8)
    assert np.subtract(s.flow_xy_rad, s.gyro_xyz_rad[:2]) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert s.gyro_xyz_rad == pytest.approx(tuple(0.02 * rates))


def test_on_the_ground_it_reads_nothing_with_quality_zero() -> None:
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.array([0.5, 0.0, 0.0]), LEVEL_NORTH, np.zeros(3), 0.0)
    assert s.quality == 0
    assert s.flow_xy_rad == (0.0, 0.0)


def test_a_tilted_sensor_sees_the_floor_farther_away() -> None:
    R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]])  # 0.3 rad roll
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.zeros(3), R, np.zeros(3), 1.0)
    assert s.distance_m == pytest.approx(1.0 / np.cos(0.3))


def test_the_message_leaves_the_distance_to_px4s_range_finder() -> None:
    s = FlowSensorModel(noise_rad_s=0.0).sample(0.02, np.array([1.0, 0.0, 0.0]), LEVEL_NORTH, np.zeros(3), 0.5)
    mav = mavlink.MAVLink(None)
    msg = mav.optical_flow_rad_encode(0, 0, **flow_rad_fields(s))
    assert msg.integration_time_us == 20000
    assert msg.distance < 0.0  # unknown: PX4 takes its own range finder
    assert msg.integrated_y == pytest.approx(0.04)


def test_integration_skips_the_first_sample_and_stalls() -> None:
    assert integration_dt(None, 1.0) is None
    assert integration_dt(1.0, 1.02) == pytest.approx(0.02)
    assert integration_dt(1.0, 1.5) is None  # a stall is no 0.5 s integration of one instant's rate


class _Sent:
    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(None)
        self.msgs: list[mavlink.MAVLink_message] = []

    def send(self, msg: mavlink.MAVLink_message) -> None:
        self.msgs.append(msg)


def test_the_truth_sends_px4_the_flow_of_its_motion(monkeypatch: pytest.MonkeyPatch) -> None:
    """SIH's truth, flying north at 1 m/s nose north 1 m up, reaches PX4 as forward flow."""
    now = [100.0]
    monkeypatch.setattr("companion.sim.px4_gps_denied.time.monotonic", lambda: now[0])
    truth = SihTruth("udpin://127.0.0.1:0", placement_around_start(CompanionConfig()), SharedSimState(),
                     flow=FlowSensorModel(noise_rad_s=0.0))
    sent = _Sent()
    truth.link = sent  # type: ignore[assignment]
    for k in range(3):
        # The first on the ground (where the truth's origin is), then 1 m up, 1 m/s north (vx in
        # cm/s), level, nose north.
        truth.handle(mavlink.MAVLink_hil_state_quaternion_message(
            0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 473977420 + 9 * k, 85455940, 488000 + (1000 if k else 0), 100, 0, 0,
            0, 0, 0, 0, 0))
        now[0] += 0.02
    flows = [m for m in sent.msgs if m.get_type() == "OPTICAL_FLOW_RAD"]
    assert truth.flow_sent == len(flows) == 2  # the first sample only starts the integration
    assert flows[-1].integrated_y == pytest.approx(0.02 / 1.0, rel=0.05)  # 1 m/s at 1 m over 20 ms
    assert flows[-1].integrated_x == pytest.approx(0.0, abs=1e-9)
