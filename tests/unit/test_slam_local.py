"""Slam2D on a synthetic 2D room: drift correction, fallback reporting, the API around it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _slam_world import cast, room_world, yaw_sweep_path

from companion.sim.odometry import OdometryDriftModel
from semmap.config import SlamConfig
from semmap.scan import BandScan
from semmap.slam import Slam2D, SlamStatus
from semmap.slam.local import OdometryCalibration
from semmap.slam.pose2d import matrix4, pose2, relative


def _fly(slam: Slam2D, n: int, drift: OdometryDriftModel, rate_hz: float = 5.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    truth = yaw_sweep_path(n, rate_hz)
    rng = np.random.default_rng(5)
    odom, est = [], []
    for i, p in enumerate(truth):
        t = i / rate_hz
        o = drift.update(t, p)
        e = slam.add_scan(t, BandScan.from_points(cast(room_world(), p, noise_m=0.005, rng=rng)), o)
        odom.append(o)
        est.append(e.pose_map)
    return truth, np.array(odom), np.array(est)


def _ate(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_slam_closes_the_loop_in_the_background_and_beats_drifting_odometry() -> None:
    # A lap and a quarter (the start is revisited) at 5 Hz; loop closure on its worker thread.
    drift = OdometryDriftModel(scale_error=0.03, heading_drift_deg_s=0.5, seed=1)
    seen: list[int] = []
    with Slam2D(SlamConfig()) as slam:
        slam.add_listener(seen.append)
        truth, odom, est = _fly(slam, 320, drift, rate_hz=5.0)
        assert slam.drain(timeout_s=120.0)
        slam.optimize()
        final = slam.trajectory()
        assert slam.loop_closures > 0
        assert len(slam.submaps()) >= 3
        assert any(s.finished for s in slam.submaps())
        assert slam.generation >= 1 and seen and seen[-1] == slam.generation
        # The correction carries a pose used live to where the optimised map puts it.
        k = 200
        stamp = k / 5.0
        T = slam.correction(stamp, est[k])
        moved = T @ matrix4(est[k])
        np.testing.assert_allclose(moved[:2, 3], slam.pose_at(stamp)[:2], atol=1e-9)
        assert slam.optimized_trajectory().shape[1] == 4
    assert _ate(odom, truth) > 0.3
    assert _ate(est, truth) < 0.5 * _ate(odom, truth)
    assert _ate(final[:, 1:], truth) < 0.05


def test_the_stats_report_the_odometry_errors_the_calibration_measured() -> None:
    # An operator reads the prior's health from them: a scale error far from the odometry's
    # own says the matches under-read the motion.
    drift = OdometryDriftModel(scale_error=0.05, heading_drift_deg_s=1.0, seed=3)
    with Slam2D(SlamConfig(), background=False) as slam:
        _fly(slam, 120, drift, rate_hz=5.0)
        stats = slam.stats()
    assert stats.odometry_scale_error == pytest.approx(0.05, abs=0.015)
    assert math.degrees(stats.odometry_heading_drift_rad_s) == pytest.approx(1.0, abs=0.3)


def test_too_few_points_is_reported_not_diverged() -> None:
    with Slam2D(SlamConfig(), background=False) as slam:
        p = pose2(3.0, 2.0, 0.0)
        slam.add_scan(0.0, BandScan.from_points(cast(room_world(), p)), p)
        est = slam.add_scan(0.1, np.array([[2.0, 0.0], [2.0, 0.1]]), pose2(3.05, 2.0, 0.0))
    assert est.status is SlamStatus.DEGENERATE_FALLBACK_ODOMETRY
    assert "scan points" in est.reason
    np.testing.assert_allclose(est.pose_map, [3.05, 2.0, 0.0], atol=1e-9)


def test_scans_within_the_match_interval_take_the_prediction_and_stay_out_of_the_submap() -> None:
    # A 30 Hz camera: every third scan is matched; the two between take the odometry's
    # increment and are neither matched, nor fed to the calibration, nor inserted.
    cfg = SlamConfig(match_interval_s=0.09, motion_filter_time_s=0.0)
    rng = np.random.default_rng(3)
    truth = pose2(3.0, 2.0, 0.0)
    with Slam2D(cfg, background=False) as slam:
        results = []
        for i in range(12):
            t = i / 30.0
            odom = truth + np.array([0.002 * i, 0.0, 0.0])  # the odometry creeps, the vehicle stands
            hits = cast(room_world(), truth, noise_m=0.005, rng=rng)
            results.append((slam.local.add_scan(t, BandScan.from_points(hits), odom), odom))
    matched = [r.matched for r, _ in results]
    first = matched.index(True)
    assert matched[first:first + 9] == [True, False, False] * 3
    for (r, odom), (prev, prev_odom) in zip(results[first + 1:], results[first:-1], strict=True):
        assert r.status is SlamStatus.OK
        if not r.matched:  # predicted: the previous pose moved by the odometry's increment
            np.testing.assert_allclose(r.pose_local[:2] - prev.pose_local[:2], odom[:2] - prev_odom[:2], atol=1e-4)
            assert not r.inserted
    assert all(r.inserted for r, _ in results[first:] if r.matched)  # motion_filter_time_s 0: every match


def test_a_first_scan_without_obstacles_does_not_leave_the_next_ones_on_the_odometry() -> None:
    # On the ground the camera sees nothing in the band: the first scan has no hits. Then
    # the vehicle is in the air, still, while the odometry's heading drifts 2 deg/s. The
    # next scan must go into the empty submap at once; waiting for the motion filter (2 s)
    # left every scan in between on the drifting odometry and the map rotated with it.
    truth = pose2(3.0, 2.0, 0.3)
    rng = np.random.default_rng(2)
    with Slam2D(SlamConfig(), background=False) as slam:
        slam.add_scan(0.0, BandScan.from_points(np.zeros((0, 2))), truth)
        statuses = []
        for i in range(1, 29):
            t = i / 15.0
            odom = truth + np.array([0.0, 0.0, math.radians(2.0) * t])
            est = slam.add_scan(t, BandScan.from_points(cast(room_world(), truth, noise_m=0.005, rng=rng)), odom)
            statuses.append(est.status)
    assert statuses[0] is SlamStatus.DEGENERATE_FALLBACK_ODOMETRY  # used at the prediction
    assert all(s is SlamStatus.OK for s in statuses[1:])
    assert abs(math.degrees(est.pose_map[2] - truth[2])) < 0.5  # the odometry is 3.7 deg off
    assert np.linalg.norm(est.pose_map[:2] - truth[:2]) < 0.02


def test_drift_model_drifts_as_specified() -> None:
    m = OdometryDriftModel(scale_error=0.03, heading_drift_deg_s=0.5, noise_m_per_sqrt_m=0.0,
                           noise_rad_per_sqrt_rad=0.0)
    out = [m.update(t, (0.1 * t, 0.0, 0.0)) for t in np.arange(0.0, 10.01, 0.1)]
    assert math.degrees(out[-1][2]) == pytest.approx(5.0, abs=1e-6)
    path = np.sum(np.linalg.norm(np.diff(np.array(out)[:, :2], axis=0), axis=1))
    assert path == pytest.approx(1.03, rel=1e-6)
    np.testing.assert_allclose(out[0], [0.0, 0.0, 0.0])


def test_odometry_calibration_measures_heading_drift_and_scale() -> None:
    # The odometry of a vehicle sweeping its yaw along a path drifts 2 deg/s and reads
    # distances 3 % long; the matched poses are the truth with 1 cm / 0.3 deg of noise.
    drift = OdometryDriftModel(scale_error=0.03, heading_drift_deg_s=2.0, seed=2)
    cal = OdometryCalibration(window_s=10.0)
    rng = np.random.default_rng(4)
    rate_hz = 10.0
    truth = yaw_sweep_path(150, rate_hz)
    odom = []
    for i, p in enumerate(truth):
        o = drift.update(i / rate_hz, p)
        odom.append(o)
        matched = p + np.array([*rng.normal(0.0, 0.01, 2), rng.normal(0.0, math.radians(0.3))])
        cal.add(i / rate_hz, o, matched)
    assert math.degrees(cal.heading_drift_rad_s) == pytest.approx(2.0, abs=0.15)
    assert cal.scale_error == pytest.approx(0.03, abs=0.01)
    # The corrected increments of the last 3 s carry neither error: their yaw adds up to the
    # true turn (the raw ones to 6 deg more) and their lengths to the true distance.
    k = range(len(truth) - 30, len(truth))
    raw = [relative(odom[i - 1], odom[i]) for i in k]
    true_inc = [relative(truth[i - 1], truth[i]) for i in k]
    fixed = [cal.correct(r, 1.0 / rate_hz) for r in raw]

    def turn_error_deg(incs: list[np.ndarray]) -> float:
        return math.degrees(sum(float(a[2] - b[2]) for a, b in zip(incs, true_inc, strict=True)))

    def length_ratio(incs: list[np.ndarray]) -> float:
        return sum(float(np.hypot(*a[:2])) for a in incs) / sum(float(np.hypot(*b[:2])) for b in true_inc)

    assert turn_error_deg(raw) == pytest.approx(6.0, abs=1.5)
    assert abs(turn_error_deg(fixed)) < 1.0
    assert length_ratio(raw) == pytest.approx(1.03, abs=0.005)
    assert length_ratio(fixed) == pytest.approx(1.0, abs=0.01)


def test_px4_gps_denied_seed1_a_turns_matching_error_is_not_taken_for_gyro_drift() -> None:
    # A fast turn is where the narrow camera matches its heading worst: its error is a step in
    # (odometry - matched), not a slope, and must not be read as gyro drift.
    drift_rad_s = math.radians(0.5)
    cal = OdometryCalibration(window_s=10.0)
    rate_hz, turn_rad_s = 20.0, math.radians(70.0)
    t_turn = (4.0, 4.0 + 2.0 * math.pi / turn_rad_s)
    for i in range(int(10.0 * rate_hz)):
        t = i / rate_hz
        yaw = turn_rad_s * min(max(t - t_turn[0], 0.0), t_turn[1] - t_turn[0])
        lag = math.radians(1.2) * (yaw / (2.0 * math.pi))  # the matcher's error builds up in the turn
        odo = np.array([0.0, 0.0, yaw + drift_rad_s * t])
        cal.add(t, odo, np.array([0.0, 0.0, yaw - lag]))
    assert math.degrees(cal.heading_drift_rad_s) == pytest.approx(0.5, abs=0.05)


def test_odometry_calibration_waits_for_enough_matches() -> None:
    cal = OdometryCalibration(window_s=10.0, min_span_s=3.0)
    for i in range(20):  # 1.9 s of matches whose odometry turns 10 deg/s faster
        t = i / 10.0
        cal.add(t, np.array([0.1 * t, 0.0, math.radians(10.0) * t]), np.array([0.1 * t, 0.0, 0.0]))
    assert cal.heading_drift_rad_s == 0.0 and cal.scale_error == 0.0


def _spin_heading_error_deg(rate_deg_per_scan: float, scans: int, seed: int) -> float:
    """Heading error after spinning in place (perfect odometry, 1 cm range noise, a
    camera-wide 87 deg field of view) in the synthetic room."""
    rng = np.random.default_rng(seed)
    x, y = 4.0, 3.0
    with Slam2D(SlamConfig(match_interval_s=0.0), background=False) as slam:  # every scan's match
        for i in range(scans):
            p = pose2(x, y, math.radians(rate_deg_per_scan * i))
            hits = cast(room_world(), p, fov_deg=87.0, n_rays=160, noise_m=0.01, rng=rng)
            est = slam.add_scan(i / 30.0, BandScan.from_points(hits), p)
    return math.degrees(math.remainder(float(est.pose_map[2]) - float(p[2]), 2.0 * math.pi))


@pytest.mark.parametrize("rate_deg_per_scan", [2.3, -2.3])
def test_px4_gps_denied_seed1_spin_heading_does_not_lag_the_turn(rate_deg_per_scan: float) -> None:
    # Turning at 70 deg/s in front of the camera, each scan's leading edge holds the next
    # stretch of wall, which the submap has not seen yet. The likelihood field pulled those
    # hits back onto the known end of the wall, so every match rotated the scan back a little:
    # the heading lagged the turn. Two revolutions; the mean over three noise seeds keeps the
    # systematic lag and averages out each run's random error.
    lag_deg = [-math.copysign(1.0, rate_deg_per_scan) * _spin_heading_error_deg(rate_deg_per_scan, 320, seed)
               for seed in (7, 8, 9)]
    assert float(np.mean(lag_deg)) < 0.3
