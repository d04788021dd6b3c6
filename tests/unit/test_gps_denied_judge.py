"""How the GPS-denied bench tells a stalled SLAM from an unmatched one
(companion.sim.px4_gps_denied_flight.scan_gaps)."""

from __future__ import annotations

import pytest

from companion.sim.px4_gps_denied_flight import SCAN_STATUS_CODES, scan_gaps

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
