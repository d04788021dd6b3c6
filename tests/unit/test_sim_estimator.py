"""The mock autopilot's estimate: drift, setpoints carried to the true frame, vision fusion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.sim.autopilot.estimator import SimEstimator, T_map_body_of
from companion.sim.autopilot.vehicle import (
    KinematicMulticopter,
    Target,
    VehicleLimits,
    VehicleState,
)
from companion.sim.odometry import OdometryDriftModel


def _state(t: float, n: float, e: float, yaw: float) -> VehicleState:
    return VehicleState(t, (n, e, -1.0), (0.3, 0.0, 0.0), 0.01, -0.02, yaw, 0.0, False)


def _drift(**kw: float) -> OdometryDriftModel:
    args = {"scale_error": 0.03, "heading_drift_deg_s": 2.0, "noise_m_per_sqrt_m": 0.0,
            "noise_rad_per_sqrt_rad": 0.0}
    args.update(kw)
    return OdometryDriftModel(**args)  # type: ignore[arg-type]


def test_without_drift_the_estimate_is_the_truth() -> None:
    est = SimEstimator()
    s = _state(1.0, 2.0, 3.0, 0.4)
    assert est.update(s) == s
    tgt = Target(position_ned_m=(1.0, 2.0, -1.0), yaw_rad=0.3)
    assert est.to_true(tgt) == tgt


def test_drift_shows_in_the_reported_state_only_horizontally() -> None:
    est = SimEstimator(_drift())
    for k in range(101):
        t = 0.1 * k
        rep = est.update(_state(t, 0.3 * t, 0.0, 0.0))
    # 10 s at 2 deg/s: the heading reads 20 deg off; 3 m flown read longer and bent.
    assert math.degrees(rep.yaw_rad) == pytest.approx(20.0, abs=0.5)
    assert math.hypot(*rep.position_ned_m[:2]) == pytest.approx(3.0 * 1.03, rel=0.01)
    assert rep.position_ned_m[1] > 0.2
    # Height, roll and pitch are not affected.
    assert rep.position_ned_m[2] == -1.0 and rep.roll_rad == 0.01 and rep.pitch_rad == -0.02
    # The reported yaw rate has the gyro bias that drifts the heading (integrated, it is the drift).
    assert math.degrees(rep.yaw_rate_rad_s) == pytest.approx(2.0)
    T = T_map_body_of(rep)
    assert T[2, 3] == pytest.approx(1.0)  # ENU up


@settings(max_examples=40, deadline=None)
@given(st.floats(-5, 5), st.floats(-5, 5), st.floats(-math.pi, math.pi))
def test_a_setpoint_at_the_reported_pose_is_the_true_pose(n: float, e: float, yaw: float) -> None:
    est = SimEstimator(_drift(heading_drift_deg_s=5.0))
    for k in range(40):
        t = 0.1 * k
        rep = est.update(_state(t, n + 0.1 * t, e, yaw))
    true = _state(3.9, n + 0.39, e, yaw)
    tgt = est.to_true(Target(position_ned_m=rep.position_ned_m, yaw_rad=rep.yaw_rad))
    assert tgt.position_ned_m is not None and tgt.yaw_rad is not None
    np.testing.assert_allclose(tgt.position_ned_m, true.position_ned_m, atol=1e-9)
    assert math.remainder(tgt.yaw_rad - yaw, math.tau) == pytest.approx(0.0, abs=1e-9)
    # Axes the setpoint does not control stay uncontrolled.
    free = est.to_true(Target(position_ned_m=(math.nan, math.nan, -1.0)))
    assert free.position_ned_m is not None and math.isnan(free.position_ned_m[0])


def test_vision_pulls_the_estimate_to_the_truth_and_repeats_are_ignored() -> None:
    est = SimEstimator(_drift(heading_drift_deg_s=3.0), vision_gain=0.5)
    truth: list[VehicleState] = []
    for k in range(200):  # 2 s at 100 Hz
        s = _state(0.01 * k, 0.3 * 0.01 * k, 0.0, 0.2)
        truth.append(s)
        est.update(s)
    drifted = est.estimated(truth[-1])
    assert abs(drifted.yaw_rad - 0.2) > math.radians(5.0)
    # Vision of the true pose 50 ms ago, once: half the error at that time is removed.
    then = truth[-6]
    assert est.fuse_vision(then.stamp_s, then.position_ned_m[0], then.position_ned_m[1], then.yaw_rad)
    assert not est.fuse_vision(then.stamp_s, then.position_ned_m[0], then.position_ned_m[1], then.yaw_rad)
    assert est.vision_fused == 1
    for k in range(200, 300):  # vision at every 10th tick keeps it there
        s = _state(0.01 * k, 0.3 * 0.01 * k, 0.0, 0.2)
        truth.append(s)
        est.update(s)
        if k % 10 == 0:
            v = truth[-4]
            est.fuse_vision(v.stamp_s, v.position_ned_m[0], v.position_ned_m[1], v.yaw_rad)
    rep = est.estimated(truth[-1])
    assert abs(rep.yaw_rad - 0.2) < math.radians(1.0)  # 0.3 deg of drift between samples
    assert math.dist(rep.position_ned_m, truth[-1].position_ned_m) < 0.01


def test_the_vehicle_flies_the_estimate_to_the_setpoint() -> None:
    # The controller drives the reported pose onto the setpoint; the airframe ends where the
    # estimate's error says, not on the setpoint.
    est = SimEstimator(vision_gain=0.5)
    veh = KinematicMulticopter(VehicleLimits(), position_ned_m=(1.0, 0.0, -1.0))
    veh.motors_on = True
    est.update(veh.state())
    # A vision sample 1 m north of the truth at gain 0.5: the estimate reads 0.5 m north.
    assert est.fuse_vision(veh.state().stamp_s, 2.0, 0.0, 0.0)
    assert est.estimated(veh.state()).position_ned_m[0] == pytest.approx(1.5)
    veh.set_target(est.to_true(Target(position_ned_m=(3.0, 0.0, -1.0))))
    for _ in range(1000):
        veh.step(0.01)
        est.update(veh.state())
    assert veh.position_ned_m[0] == pytest.approx(2.5, abs=0.02)
    assert est.estimated(veh.state()).position_ned_m[0] == pytest.approx(3.0, abs=0.02)
