"""Which SLAM poses the service sends to PX4 as external vision (companion.service.localization)."""

from __future__ import annotations

import math
import os
import threading

import numpy as np
import pytest

from companion.service.localization import (
    _STATUS_CODES,
    JumpCounter,
    SharedLocalization,
)
from companion.service.position_source import VisionPoseSource, vision_pose
from semmap.slam import SlamStatus


def _shared(status: SlamStatus) -> SharedLocalization:
    shared = SharedLocalization()
    shared.publish({"stamp_s": 12.5, "x_m": 1.0, "y_m": -2.0, "z_m": 0.6, "yaw_rad": 0.3,
                    "status": _STATUS_CODES[status], "generation": 3, "resets": 2})
    return shared


def test_the_status_carries_the_odometry_errors_the_slam_removes() -> None:
    shared = SharedLocalization()
    shared.publish({"stamp_s": 1.0, "status": _STATUS_CODES[SlamStatus.OK], "odometry_scale_error": 0.031,
                    "odometry_heading_drift_rad_s": math.radians(0.5)})
    st = shared.latest()
    assert st is not None
    summary = st.summary()
    assert summary["odometry_scale_error"] == pytest.approx(0.031)
    assert summary["odometry_heading_drift_deg_s"] == pytest.approx(0.5)


def test_a_fully_matched_pose_is_sent() -> None:
    pose = vision_pose(_shared(SlamStatus.OK))
    assert pose is not None
    assert pose.stamp_s == 12.5 and pose.quality_percent == 100 and pose.reset_counter == 2
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


def test_the_pose_carries_its_errors_and_a_reset_after_a_gap() -> None:
    now = [100.0]
    source = VisionPoseSource(_shared(SlamStatus.OK), position_std_m=0.05, yaw_std_rad=0.03,
                              reset_after_gap_s=1.0, clock=lambda: now[0])
    first = source()
    assert first is not None and (first.position_std_m, first.yaw_std_rad) == (0.05, 0.03)
    now[0] += 0.5
    assert source().reset_counter == 2  # type: ignore[union-attr]
    # PX4 dead-reckoned on its IMU for 1.5 s: it must take the next pose as it is.
    now[0] += 1.5
    assert source().reset_counter == 3  # type: ignore[union-attr]
    assert source.gap_resets == 1


def test_jumps_of_the_matched_pose_are_counted() -> None:
    jumps = JumpCounter(jump_m=0.10, jump_rad=math.radians(3.0))
    odom = np.array([0.0, 0.0, 0.0])
    pose = np.array([5.0, 1.0, 0.5])
    assert jumps.update(pose, odom, True) == 0
    # Moving 0.3 m forward by odometry, matched 2 cm off that prediction: scan matching, no jump.
    fwd = np.array([0.3, 0.0, 0.0])
    pred = pose + np.array([0.3 * math.cos(0.5), 0.3 * math.sin(0.5), 0.0])
    assert jumps.update(pred + [0.02, 0.0, 0.0], fwd, True) == 0
    # A loop closure moves the pose 0.25 m at once.
    assert jumps.update(pred + [0.27, 0.0, 0.0], fwd, True) == 1
    # Turned 5 degrees more than the odometry says.
    assert jumps.update(pred + [0.27, 0.0, math.radians(5.0)], fwd, True) == 2
    # Fallback poses are neither compared nor remembered.
    assert jumps.update(np.array([50.0, 50.0, 0.0]), fwd, False) == 2
    assert jumps.update(pred + [0.27, 0.0, math.radians(5.0)], fwd, True) == 2


def test_the_slam_process_hands_the_gil_over_often() -> None:
    # The SLAM shares its process with detection: at the default 5 ms switch interval its short
    # numpy calls queued behind detection's Python and the pose rate PX4 needs fell apart.
    import sys

    from companion.config import CompanionConfig
    from companion.service.localization import SLAM_SWITCH_INTERVAL_S, LocalizedFrameSource
    from companion.sources.base import FrameSource

    class _Camera(FrameSource):
        intrinsics = CompanionConfig().camera.intrinsics()

        def open(self) -> None:
            pass

        def read(self) -> None:
            return None

    before = sys.getswitchinterval()
    src = LocalizedFrameSource(_Camera(), CompanionConfig())
    try:
        src.open()
        assert sys.getswitchinterval() == pytest.approx(SLAM_SWITCH_INTERVAL_S)
    finally:
        src.close()
        sys.setswitchinterval(before)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="undoing a nice needs CAP_SYS_NICE")
def test_the_slam_thread_does_not_yield_with_the_niced_perception_process() -> None:
    # Under load (average 13-16 on 2 cores) the niced perception process published 1-5 SLAM
    # poses/s; EKF2 stopped fusing vision and PX4 fell back to Altitude mode.
    from companion.service.localization import reader_thread_at_parent_priority

    parent = os.getpriority(os.PRIO_PROCESS, os.getppid())
    seen: list[int] = []

    def reader() -> None:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(parent + 5, 19))  # as the perception process is niced
        reader_thread_at_parent_priority()
        seen.append(os.getpriority(os.PRIO_PROCESS, tid))

    t = threading.Thread(target=reader)
    t.start()
    t.join()
    assert seen == [parent]


def _partial(since_match_m: float, prior_odometry: bool = True,
             status: SlamStatus = SlamStatus.PARTIAL_ODOMETRY) -> SharedLocalization:
    shared = SharedLocalization()
    shared.publish({"stamp_s": 3.0, "x_m": 1.0, "y_m": 2.0, "status": _STATUS_CODES[status],
                    "since_match_m": since_match_m, "prior_odometry": 1.0 if prior_odometry else 0.0})
    return shared


def test_a_partial_pose_on_an_independent_odometry_goes_with_a_grown_error() -> None:
    source = VisionPoseSource(_partial(2.0), position_std_m=0.05, odometry_independent=True,
                              odometry_drift_per_m=0.05)
    pose = source()
    assert pose is not None and pose.stamp_s == 3.0
    assert pose.position_std_m == pytest.approx(math.hypot(0.05, 0.10))
    assert source.partial_sends == 1


def test_a_partial_pose_is_held_back_unless_its_odometry_is_the_vehicles_own() -> None:
    # The default: the odometry may be PX4's own velocity, which the vision corrected.
    assert VisionPoseSource(_partial(0.5), position_std_m=0.05)() is None
    # Switched on, but this prior is the autopilot's estimate (frames without odometry).
    assert VisionPoseSource(_partial(0.5, prior_odometry=False), position_std_m=0.05,
                            odometry_independent=True)() is None


def test_a_partial_pose_carried_too_far_by_odometry_stops() -> None:
    source = VisionPoseSource(_partial(10.0), position_std_m=0.05, odometry_independent=True,
                              odometry_drift_per_m=0.05)
    assert source() is None


def test_a_scan_that_matched_nothing_is_dead_reckoned_on_an_independent_odometry() -> None:
    source = VisionPoseSource(_partial(1.0, status=SlamStatus.DEGENERATE_FALLBACK_ODOMETRY), position_std_m=0.05,
                              yaw_std_rad=0.03, odometry_independent=True, odometry_drift_per_m=0.05)
    pose = source()
    assert pose is not None
    assert pose.position_std_m == pytest.approx(math.hypot(0.05, 0.05))
    assert pose.yaw_std_rad == pytest.approx(math.hypot(0.03, 0.05))
    # The configured pure-odometry mode is no SLAM pose at all.
    assert VisionPoseSource(_partial(0.0, status=SlamStatus.ODOMETRY), position_std_m=0.05,
                            odometry_independent=True)() is None


def test_a_pose_too_old_for_ekf2_to_fuse_is_not_sent() -> None:
    # Captured at 3.0 s: at 3.25 s it is inside EKF2's fusion window, at 3.4 s past it
    # (PX4 drops it, so the loss guard must not count it as sent).
    now = [3.25]
    shared = _partial(0.0, status=SlamStatus.OK)
    source = VisionPoseSource(shared, position_std_m=0.05, fusion_window_s=0.3, clock=lambda: now[0])
    assert source() is not None
    now[0] = 3.4
    assert source() is None and source.too_late == 1


def test_the_perception_process_is_niced_only_without_the_slam_in_it() -> None:
    from companion.config import CompanionConfig
    from companion.service.perception_process import PERCEPTION_NICE, perception_nice

    cfg = CompanionConfig()
    assert perception_nice(cfg) == PERCEPTION_NICE
    slam = cfg.model_copy(update={"service": cfg.service.model_copy(update={"localization": "slam"})})
    assert perception_nice(slam) == 0
