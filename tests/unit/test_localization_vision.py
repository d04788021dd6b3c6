"""Which SLAM poses the service sends to PX4 as external vision (companion.service.localization)."""

from __future__ import annotations

import pytest

from companion.service.localization import _STATUS_CODES, SharedLocalization, vision_pose
from semmap.slam import SlamStatus


def _shared(status: SlamStatus) -> SharedLocalization:
    shared = SharedLocalization()
    shared.publish({"stamp_s": 12.5, "x_m": 1.0, "y_m": -2.0, "z_m": 0.6, "yaw_rad": 0.3,
                    "status": _STATUS_CODES[status], "generation": 3})
    return shared


def test_a_fully_matched_pose_is_sent() -> None:
    pose = vision_pose(_shared(SlamStatus.OK))
    assert pose is not None
    assert pose.stamp_s == 12.5 and pose.quality_percent == 100 and pose.reset_counter == 3
    assert pose.T_map_body[:3, 3] == pytest.approx([1.0, -2.0, 0.6])


@pytest.mark.parametrize("status", [SlamStatus.PARTIAL_ODOMETRY, SlamStatus.DEGENERATE_FALLBACK_ODOMETRY,
                                    SlamStatus.ODOMETRY])
def test_a_pose_taken_from_odometry_is_not_fed_back(status: SlamStatus) -> None:
    # Regression (test_service_slam, ~1 run in 10): partly matched poses went to PX4 with
    # quality 50; along the free direction they echo PX4's own estimate, and the fusion and
    # the SLAM's prediction then chased each other (4.5 cm -> 0.26 m in eleven scans).
    assert vision_pose(_shared(status)) is None


def test_nothing_before_the_first_scan_or_when_stale() -> None:
    assert vision_pose(SharedLocalization()) is None
    assert vision_pose(_shared(SlamStatus.OK), max_age_s=-1.0) is None
