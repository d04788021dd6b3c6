"""The GPS-denied bench's records: how it tells a stalled SLAM from an unmatched one
(companion.sim.px4_gps_denied_flight.scan_gaps) and the truth it keeps."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from companion.config import CompanionConfig
from companion.sim.px4_gps_denied import SihTruth, placement_around_start
from companion.sim.px4_gps_denied_flight import SCAN_STATUS_CODES, scan_gaps
from companion.sim.sim_world import SharedSimState

OK, PARTIAL = SCAN_STATUS_CODES["ok"], SCAN_STATUS_CODES["partial_odometry"]


def _scans(statuses: list[tuple[float, int]], latency_s: float = 0.05) -> list[tuple[float, float, int, float]]:
    return [(t, t + latency_s, code, 5.0) for t, code in statuses]


def test_a_stall_and_a_run_of_unmatched_scans_are_told_apart() -> None:
    t = [(0.1 * k, OK) for k in range(10)]  # 10 Hz, all matched
    t += [(1.0 + 0.1 * k, PARTIAL) for k in range(8)]  # 0.8 s of partly matched scans
    t += [(1.8, OK), (2.6, OK)]  # then nothing at all for 0.8 s
    t += [(2.7 + 0.1 * k, OK) for k in range(5)]
    gaps = scan_gaps(_scans(t))
    assert gaps["unmatched"] == 1 and gaps["no_scan"] == 1
    assert gaps["longest_s"] == pytest.approx(0.9)
    assert gaps["capture_to_publish_ms_p50"] == pytest.approx(50.0)


def test_a_steady_stream_has_no_gaps() -> None:
    gaps = scan_gaps(_scans([(0.1 * k, OK) for k in range(50)]))
    assert (gaps["no_scan"], gaps["unmatched"]) == (0, 0)
    assert gaps["scan_rate_hz"] == pytest.approx(10.2, abs=0.3)


def test_the_truth_keeps_the_attitude_the_camera_was_rendered_with() -> None:
    # A flight is replayed offline from its tracks; without the true roll and pitch the replay
    # can only guess the tilt from the accelerations.
    roll, pitch, yaw = 0.1, -0.05, 0.3  # FRD body in NED
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    msg = mavlink.MAVLink_hil_state_quaternion_message(0, [w, x, y, z], 0, 0, 0, 473977420, 85455940, 488000,
                                                       0, 0, 0, 0, 0, 0, 0, 0)
    truth = SihTruth("udpin://127.0.0.1:0", placement_around_start(CompanionConfig()), SharedSimState())
    truth.handle(msg)
    s = truth.samples[-1]
    # FRD -> FLU: roll keeps its sign, pitch and yaw flip (yaw also measured from east).
    assert (s.roll_rad, s.pitch_rad) == (pytest.approx(roll, abs=1e-9), pytest.approx(-pitch, abs=1e-9))
    assert s.yaw_rad == pytest.approx(math.pi / 2 - yaw, abs=1e-9)
