"""Pure parts of the companion service: mission legs, frame sanity checks, checkpoints, the
SLAM's motion prior."""

from __future__ import annotations

import gc
import math
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig
from companion.errors import MissionError
from companion.mavlink.state import HomePosition
from companion.missions import LOCAL_SCALE, MissionItemInt
from companion.service.app import frozen_heap
from companion.service.checkpoint import checkpoint_path, restore_map
from companion.service.localization import Localizer
from companion.service.mission_runner import SURVEY_CARROT_DEG, SurveyTurn, mission_legs
from companion.service.perception_worker import check_frame, new_semantic_map
from companion.sim.sim_world import SharedSimState
from semmap.errors import FrameError
from semmap.frames import pose_from_xyz_rpy
from semmap.slam import SlamStatus
from semmap.types import CameraIntrinsics, Frame

HOME = HomePosition(47.397742, 8.545594, 488.0, (0.0, 0.0, 0.0))


def _item(seq: int, cmd: int, frame: int = mavlink.MAV_FRAME_LOCAL_NED, x: float = 0.0, y: float = 0.0,
          z: float = -1.0, acc: float = 0.0) -> MissionItemInt:
    return MissionItemInt(seq, frame, cmd, 0, 1, 0.0, acc, 0.0, 0.0, round(x * LOCAL_SCALE), round(y * LOCAL_SCALE), z)


def test_mission_legs_keep_waypoints_in_the_map_frame() -> None:
    items = [
        _item(0, mavlink.MAV_CMD_NAV_TAKEOFF),
        _item(1, mavlink.MAV_CMD_NAV_WAYPOINT, x=2.0, y=1.0, acc=0.5),  # north 2, east 1
        _item(2, mavlink.MAV_CMD_DO_CHANGE_SPEED),
        _item(3, mavlink.MAV_CMD_NAV_WAYPOINT, x=-1.0, y=3.0),
        _item(4, mavlink.MAV_CMD_NAV_LAND),
    ]
    legs = mission_legs(items, HOME, altitude_m=0.6)
    assert [leg.seq for leg in legs] == [1, 3]
    assert legs[0].goal_xy_m == pytest.approx((1.0, 2.0))  # ENU: x east, y north
    assert legs[0].acceptance_m == 0.5 and legs[1].acceptance_m == 0.3
    assert all(leg.altitude_m == 0.6 for leg in legs)


def test_a_mission_without_waypoints_is_an_error() -> None:
    with pytest.raises(MissionError, match="no waypoint"):
        mission_legs([_item(0, mavlink.MAV_CMD_NAV_TAKEOFF)], HOME, 0.6)


def _frame(depth: np.ndarray) -> Frame:
    h, w = depth.shape
    return Frame(0.0, np.zeros((h, w, 3), np.uint8), depth.astype(np.float32),
                 CameraIntrinsics(50.0, 50.0, w / 2, h / 2, w, h), np.eye(4))


def test_frames_with_too_little_valid_depth_are_rejected() -> None:
    good = np.full((20, 30), 2.0)
    check_frame(_frame(good), 0.3, 6.0)
    bad = good.copy()
    bad[:, :27] = np.nan
    with pytest.raises(FrameError, match="valid"):
        check_frame(_frame(bad), 0.3, 6.0)
    with pytest.raises(FrameError, match="valid"):
        check_frame(_frame(np.full((20, 30), 40.0)), 0.3, 6.0)
    f = _frame(good)
    f.T_map_camera[0, 3] = np.nan  # type: ignore[index]
    with pytest.raises(FrameError, match="pose"):
        check_frame(f, 0.3, 6.0)


def test_checkpoint_round_trip_and_a_damaged_one_is_set_aside(tmp_path: Path) -> None:
    cfg = CompanionConfig().model_copy(update={"service": CompanionConfig().service.model_copy(
        update={"map_dir": str(tmp_path)})})
    path = checkpoint_path(cfg)
    assert restore_map(cfg, path) is None
    new_semantic_map(cfg).save(path)
    assert restore_map(cfg, path) is not None
    path.write_bytes(b"not a map")
    assert restore_map(cfg, path) is None
    assert not path.exists() and path.with_suffix(".npz.bad").is_file()


def test_survey_turn_leads_the_heading_one_way_and_ends_at_the_full_turn() -> None:
    """A slow autopilot (30 deg per step, the carrot's size): the setpoint stays one carrot
    ahead, never wraps back past the vehicle, and the turn ends within 5 deg of 360."""
    turn = SurveyTurn(yaw0_rad=3.0, total_rad=2 * math.pi, yaw_rate_rad_s=math.radians(60))
    heading, steps = 3.0, 0
    while (sp := turn.next_yaw(heading)) is not None:
        ahead = math.remainder(sp - heading, 2 * math.pi)
        assert 0.0 < ahead <= math.radians(SURVEY_CARROT_DEG) + 1e-9
        heading = math.remainder(heading + 0.8 * ahead, 2 * math.pi)  # the vehicle lags
        steps += 1
        assert steps < 200
    assert math.degrees(turn.turned_rad) >= 355.0
    assert turn.final_yaw_rad == math.remainder(3.0 + 2 * math.pi, 2 * math.pi)
    assert turn.next_yaw(None) is None  # no new heading: still done


def test_frozen_heap_keeps_the_collector_off_live_objects_and_restores_an_outer_freeze() -> None:
    assert gc.get_freeze_count() == 0
    with frozen_heap():
        assert gc.get_freeze_count() > 1000  # the imported modules' objects at least
        cycle: list[object] = []
        cycle.append(cycle)  # garbage made after the freeze is still collected
        del cycle
        assert gc.collect() >= 1
    assert gc.get_freeze_count() == 0
    gc.freeze()
    try:
        outer = gc.get_freeze_count()
        with frozen_heap():
            pass
        assert gc.get_freeze_count() >= outer  # the caller's freeze is not undone
    finally:
        gc.unfreeze()


def test_slam_motion_prior_is_the_odometry_anchored_on_the_estimate_and_never_the_fused_estimate() -> None:
    """The autopilot's estimate fuses the SLAM's vision; the prior must move with the
    frame's odometry only, in the map frame the estimate had at the first scan."""
    cfg = CompanionConfig()
    intr = cfg.camera.intrinsics()
    loc = Localizer(cfg, intr)
    try:
        def frame(i: int, odo: tuple[float, float, float] | None) -> Frame:
            T = None if odo is None else pose_from_xyz_rpy(odo[0], odo[1], 1.0, 0.0, 0.0, odo[2])
            return Frame(0.1 * i, np.zeros((2, 2, 3), np.uint8), np.ones((2, 2), np.float32), intr, None, i,
                         T_odom_body=T)

        # First frame: odometry frame rotated 90 deg and shifted against the estimate's frame.
        p0 = loc.odometry_prior(frame(0, (10.0, 5.0, math.pi / 2)), (1.0, 2.0, 0.0))
        np.testing.assert_allclose(p0, [1.0, 2.0, 0.0], atol=1e-12)
        assert loc.prior_source == "odometry"
        # The odometry moved 0.5 m forward (its +y); the estimate jumped 0.3 m (vision fused):
        # the prior moves 0.5 m forward in the map (+x), none of the jump.
        p1 = loc.odometry_prior(frame(1, (10.0, 5.5, math.pi / 2)), (1.5, 2.3, 0.0))
        np.testing.assert_allclose(p1, [1.5, 2.0, 0.0], atol=1e-12)
        # A frame without odometry: the estimate takes over from where the prior was.
        p2 = loc.odometry_prior(frame(2, None), (1.6, 2.3, 0.0))
        np.testing.assert_allclose(p2, [1.5, 2.0, 0.0], atol=1e-12)
        assert loc.prior_source == "estimate"
        p3 = loc.odometry_prior(frame(3, None), (1.7, 2.3, 0.1))
        np.testing.assert_allclose(p3, [1.6, 2.0, 0.1], atol=1e-12)
    finally:
        loc.close()


def test_the_distance_since_the_last_full_match_follows_the_prior_and_restarts_on_a_match() -> None:
    loc = Localizer(CompanionConfig(), CompanionConfig().camera.intrinsics())
    try:
        assert loc.since_match_m(np.array([0.0, 0.0, 0.0]), SlamStatus.OK) == 0.0
        assert loc.since_match_m(np.array([0.3, 0.4, 0.2]), SlamStatus.PARTIAL_ODOMETRY) == pytest.approx(0.5)
        assert loc.since_match_m(np.array([0.6, 0.8, 0.2]), SlamStatus.PARTIAL_ODOMETRY) == pytest.approx(1.0)
        assert loc.since_match_m(np.array([0.6, 0.9, 0.2]), SlamStatus.OK) == 0.0
        assert loc.since_match_m(np.array([0.6, 1.1, 0.2]), SlamStatus.PARTIAL_ODOMETRY) == pytest.approx(0.2)
    finally:
        loc.close()


def test_sim_state_carries_the_estimate_and_the_odometry_pose_together() -> None:
    shared = SharedSimState()
    assert shared.poses() is None
    truth, est, odo = (pose_from_xyz_rpy(1.0, 2.0, 1.0), pose_from_xyz_rpy(1.1, 2.0, 1.0, 0.0, 0.0, 0.1),
                       pose_from_xyz_rpy(5.0, 0.0, 1.0, 0.0, 0.0, 1.0))
    shared.set_pose(3.0, truth, est, odo)
    p = shared.poses()
    assert p is not None and p.monotonic_s == 3.0
    np.testing.assert_array_equal(p.T_map_body, truth)
    assert p.T_map_body_estimated is not None and p.T_odom_body is not None
    np.testing.assert_array_equal(p.T_map_body_estimated, est)
    np.testing.assert_array_equal(p.T_odom_body, odo)
    shared.set_pose(3.1, truth)  # an exact estimate: neither is published
    p = shared.poses()
    assert p is not None and p.T_map_body_estimated is None and p.T_odom_body is None
