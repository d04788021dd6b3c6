"""Frames without a pose posed from the autopilot's telemetry (companion.sources.poses)."""

from __future__ import annotations

import math
import multiprocessing as mp
import threading
import time
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.mavlink.state import VehicleStateTracker
from companion.mavlink.timesync import AutopilotClock
from companion.sources.base import FrameSource
from companion.sources.poses import (
    BootClock,
    PoseTrack,
    SharedPoseHistory,
    TelemetryPosedSource,
    TelemetryPoseRecorder,
)
from semmap.frames import map_pose_from_ned, ned_pose_from_map, pose_from_xyz_rpy, rpy_from_rotation
from semmap.types import CameraIntrinsics, Frame

INTR = CameraIntrinsics(5.0, 5.0, 4.0, 3.0, 8, 6)


def _frame(stamp_s: float, index: int = 0, T: np.ndarray | None = None) -> Frame:
    return Frame(stamp_s, np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.float32), INTR, T, index)


class _Camera(FrameSource):
    def __init__(self, frames: list[Frame]) -> None:
        self.frames = list(frames)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return INTR

    def read(self) -> Frame | None:
        return self.frames.pop(0) if self.frames else None


def test_track_interpolates_position_linearly_and_attitude_by_slerp() -> None:
    a = pose_from_xyz_rpy(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    b = pose_from_xyz_rpy(1.0, 2.0, 1.0, 0.0, 0.0, math.radians(90))
    track = PoseTrack(np.array([10.0, 10.1]), [a, b], max_gap_s=0.25)
    T = track.at(10.025)
    assert T is not None
    np.testing.assert_allclose(T[:3, 3], [0.25, 0.5, 1.0], atol=1e-12)
    assert rpy_from_rotation(T[:3, :3])[2] == pytest.approx(math.radians(22.5), abs=1e-9)
    np.testing.assert_allclose(track.at(10.1), b, atol=1e-12)
    assert track.at(9.99) is None and track.at(10.11) is None  # outside the span: no guess
    assert PoseTrack(np.array([0.0, 1.0]), [a, b], max_gap_s=0.25).at(0.5) is None  # across a gap
    assert PoseTrack(np.zeros(0), np.zeros((0, 4, 4)), max_gap_s=0.25).at(0.0) is None


def _read_in_child(hist: SharedPoseHistory, go: Any, out: Any) -> None:
    go.wait(60)
    T = hist.track(2.0).at(5.5)
    out.put((hist.latest_stamp_s(), None if T is None else float(T[0, 3])))


def test_history_is_a_ring_of_increasing_stamps_and_survives_pickling() -> None:
    hist = SharedPoseHistory(capacity=4)
    for i in range(6):
        assert hist.push(float(i), pose_from_xyz_rpy(float(i), 0.0, 0.0))
    assert not hist.push(5.0, np.eye(4))  # not newer
    assert not hist.push(6.0, np.full((4, 4), np.nan))  # not finite
    assert len(hist) == 4 and hist.latest_stamp_s() == 5.0
    track = hist.track(max_gap_s=2.0)
    np.testing.assert_allclose(track.t, [2.0, 3.0, 4.0, 5.0])
    T = track.at(3.5)
    assert T is not None and T[0, 3] == pytest.approx(3.5)
    # A frame's lookup (the two samples around it) gives what the whole track gives.
    for t in (1.5, 2.0, 3.5, 5.0, 5.5):
        a, b = track.at(t), hist.pose_at(t, 2.0)
        assert (a is None and b is None) or np.allclose(a, b), t
    # The perception process (spawned) reads what this one appends.
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    go = ctx.Event()
    child = ctx.Process(target=_read_in_child, args=(hist, go, out))
    child.start()
    try:
        hist.push(6.0, pose_from_xyz_rpy(6.0, 0.0, 0.0))
        go.set()
        assert out.get(timeout=60) == (6.0, pytest.approx(5.5))
    finally:
        child.join(30)
    with pytest.raises(ValueError, match="capacity"):
        SharedPoseHistory(capacity=1)


def test_map_pose_from_ned_inverts_the_vision_conversion() -> None:
    T = pose_from_xyz_rpy(1.0, -2.0, 1.5, 0.1, -0.2, 2.5)
    p_ned, R_ned_frd = ned_pose_from_map(T)
    roll, pitch, yaw = rpy_from_rotation(R_ned_frd)
    np.testing.assert_allclose(map_pose_from_ned(tuple(p_ned), (roll, pitch, yaw)), T, atol=1e-12)
    # North 1 m, east 2 m, 1 m up, heading east: map x = east, y = north, yaw 0 (facing +x).
    T2 = map_pose_from_ned((1.0, 2.0, -1.0), (0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(T2[:3, 3], [2.0, 1.0, 1.0], atol=1e-12)
    assert rpy_from_rotation(T2[:3, :3])[2] == pytest.approx(0.0, abs=1e-12)


def _mav() -> mavlink.MAVLink:
    return mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def _decoded(mav: mavlink.MAVLink, msg: mavlink.MAVLink_message, src: tuple[int, int] = (1, 1)) -> mavlink.MAVLink_message:
    mav.srcSystem, mav.srcComponent = src
    return mav.decode(bytearray(msg.pack(mav)))


def test_boot_clock_takes_the_least_delayed_arrival_and_restarts_on_reboot() -> None:
    clock = BootClock()
    # Sent at boot times 10.00, 10.02, ...; arrived 5 ms later, one 40 ms later (a busy loop).
    assert clock.to_local(10.00, 1000.005) == pytest.approx(1000.005)
    assert clock.to_local(10.02, 1000.060) == pytest.approx(1000.025, abs=1e-5)  # not the late arrival
    assert clock.to_local(10.04, 1000.042) == pytest.approx(1000.042)  # a quicker one lowers it
    # The offset may creep up at the crystals' drift rate, no faster.
    assert clock.to_local(110.04, 1100.1) == pytest.approx(1100.042 + 1e-4 * (1100.1 - 1000.042), abs=1e-9)
    # The autopilot rebooted: boot time restarts from zero.
    assert clock.to_local(0.5, 1200.0) == pytest.approx(1200.0)


def _home(mav: mavlink.MAVLink, z_ned_m: float) -> mavlink.MAVLink_home_position_message:
    return mav.home_position_encode(473977420, 85455940, 488000, 0.0, 0.0, z_ned_m, [1.0, 0.0, 0.0, 0.0],
                                    0.0, 0.0, 0.0)


def test_boot_clock_follows_an_autopilot_clock_one_percent_slow() -> None:
    """A lockstep PX4 SITL ran at 0.993x wall clock; a 100 ppm allowance lost the telemetry
    poses within 15 s. TIMESYNC round trips give the rate; the stamps then stay on time."""
    rate = 0.99  # autopilot seconds per local second
    ac = AutopilotClock(link=None, target_system=1)  # type: ignore[arg-type]
    clock = BootClock(remote_to_local=ac.to_local)
    rng = np.random.default_rng(0)
    errors = []
    for k in range(600):  # 60 s of telemetry at 10 Hz, a round trip every 0.5 s
        local = 1000.0 + 0.1 * k
        remote = 5.0 + rate * (local - 1000.0)
        latency = 0.002 + 0.03 * rng.random()
        if k % 5 == 0:
            ac.add_sample(remote + rate * 0.001, local, local + 0.002 + 0.01 * rng.random())
        errors.append(clock.to_local(remote, local + latency) - local)
    assert ac.rate == pytest.approx(1.0 / rate, abs=1e-3)
    assert max(abs(e) for e in errors[100:]) < 0.01


def test_recorder_makes_one_sample_per_attitude_with_the_position_moved_on() -> None:
    now = [100.0]
    hist = SharedPoseHistory(16)
    tracker = VehicleStateTracker()
    rec = TelemetryPoseRecorder(hist, clock=lambda: now[0], map_frame=lambda: tracker.snapshot().map_frame)
    mav = _mav()
    rec.handle(_decoded(mav, mav.attitude_encode(0, 0.0, 0.0, 0.0, 0, 0, 0)))
    assert len(hist) == 0  # no position yet
    rec.handle(_decoded(mav, mav.local_position_ned_encode(1000, 1.0, 2.0, -1.86, 1.0, 0.0, 0.0)))
    rec.handle(_decoded(mav, mav.attitude_encode(1000, 0.0, 0.0, 0.0, 0, 0, 0)))
    assert len(hist) == 0  # no home yet: no height above the floor
    # PX4's local origin is not the floor: home (where it stood) is 0.86 m "up" in local z.
    tracker.handle(_decoded(mav, _home(mav, -0.86)))
    now[0] = 100.05  # arrived late: the stamp is the message's own time on our clock
    rec.handle(_decoded(mav, mav.attitude_encode(1020, 0.0, 0.0, math.pi / 2, 0, 0, 0)))
    stamp = hist.latest_stamp_s()
    assert len(hist) == 1 and stamp == pytest.approx(100.02, abs=1e-3)
    T = hist.track(1.0).at(stamp)
    assert T is not None
    # North 1.02 m (1 m/s for 20 ms) -> map y; east 2 m -> map x.
    np.testing.assert_allclose(T[:3, 3], [2.0, 1.02, 1.0], atol=1e-3)  # 1 m above home
    # Another sender's messages, a stale position and a NaN attitude make no sample.
    rec.handle(_decoded(mav, mav.attitude_encode(1040, 0.0, 0.0, 0.1, 0, 0, 0), src=(255, 190)))
    now[0] = 100.5
    rec.handle(_decoded(mav, mav.attitude_encode(1500, 0.0, 0.0, 0.1, 0, 0, 0)))
    rec.handle(_decoded(mav, mav.local_position_ned_encode(1510, 1.0, 2.0, -1.86, 0.0, 0.0, 0.0)))
    rec.handle(_decoded(mav, mav.attitude_encode(1520, math.nan, 0.0, 0.1, 0, 0, 0)))
    assert len(hist) == 1 and rec.samples == 1


def test_posed_source_interpolates_waits_for_telemetry_and_counts_what_it_cannot_pose() -> None:
    hist = SharedPoseHistory(16)
    T_body_camera = pose_from_xyz_rpy(0.1, 0.0, 0.0, -math.pi / 2, 0.0, -math.pi / 2)
    hist.push(1.0, pose_from_xyz_rpy(0.0, 0.0, 1.0))
    hist.push(1.1, pose_from_xyz_rpy(1.0, 0.0, 1.0))
    given = pose_from_xyz_rpy(5.0, 5.0, 5.0)
    cam = _Camera([_frame(1.05, 0), _frame(0.5, 1), _frame(1.2, 2), _frame(7.0, 3, given)])
    src = TelemetryPosedSource(cam, hist, T_body_camera, wait_s=0.5)
    f0 = src.read()
    assert f0 is not None and f0.T_map_camera is not None
    np.testing.assert_allclose(f0.T_map_camera, pose_from_xyz_rpy(0.5, 0.0, 1.0) @ T_body_camera, atol=1e-12)
    f1 = src.read()  # before the history: no pose, no guess
    assert f1 is not None and f1.T_map_camera is None and src.unposed_frames == 1
    # Newer than the newest sample: waits for the next one, then interpolates.
    threading.Timer(0.1, lambda: hist.push(1.3, pose_from_xyz_rpy(3.0, 0.0, 1.0))).start()
    t0 = time.monotonic()
    f2 = src.read()
    assert 0.05 < time.monotonic() - t0 < 0.45
    assert f2 is not None and f2.T_map_camera is not None
    np.testing.assert_allclose(f2.T_map_camera[:3, 3], (pose_from_xyz_rpy(2.0, 0.0, 1.0) @ T_body_camera)[:3, 3],
                               atol=1e-9)
    f3 = src.read()  # a frame that has a pose keeps it
    assert f3 is not None and f3.T_map_camera is given
    assert src.read() is None
    assert (src.posed_frames, src.unposed_frames) == (2, 1)
    # No telemetry arrives: the frame waits wait_s, then goes on without a pose.
    lonely = TelemetryPosedSource(_Camera([_frame(9.0)]), hist, T_body_camera, wait_s=0.05)
    f = lonely.read()
    assert f is not None and f.T_map_camera is None and lonely.unposed_frames == 1


def test_recorder_dead_reckons_odometry_that_ignores_vision_corrections_of_the_position() -> None:
    """The position estimate jumps when PX4 fuses the companion's vision; the odometry pose,
    integrated from the velocity and the yaw rate, does not (the SLAM's motion prior)."""
    now = [0.0]
    hist = SharedPoseHistory(64)
    rec = TelemetryPoseRecorder(hist, clock=lambda: now[0])  # local origin on the floor
    mav = _mav()
    # Flying east (map +x) at 1 m/s, heading east (NED yaw pi/2), for 0.5 s.
    for k in range(51):
        t_ms = 10 * k
        now[0] = t_ms * 1e-3
        jump = 0.3 if t_ms >= 250 else 0.0  # vision moved the estimate 0.3 m north at 0.25 s
        rec.handle(_decoded(mav, mav.local_position_ned_encode(t_ms, jump, 0.001 * t_ms, -1.0, 0.0, 1.0, 0.0)))
        rec.handle(_decoded(mav, mav.attitude_encode(t_ms, 0.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0)))
    odo = hist.odometry_at(0.5, 0.1)
    assert odo is not None
    # Started on the estimate (0, 0, yaw 0 in ENU); moved 0.5 m east, none of the jump.
    np.testing.assert_allclose(odo, [0.5, 0.0, 0.0], atol=1e-6)  # MAVLink floats are float32
    T = hist.pose_at(0.5, 0.1)
    assert T is not None and T[1, 3] == pytest.approx(0.3)  # the estimate has the jump
    # Turning on the spot at 0.2 rad/s (NED yawspeed, clockwise seen from above) for 0.5 s:
    # the odometry's yaw follows the rate, its position stays.
    for k in range(1, 51):
        t_ms = 500 + 10 * k
        now[0] = t_ms * 1e-3
        rec.handle(_decoded(mav, mav.local_position_ned_encode(t_ms, 0.3, 0.5, -1.0, 0.0, 0.0, 0.0)))
        rec.handle(_decoded(mav, mav.attitude_encode(t_ms, 0.0, 0.0, math.pi / 2 + 0.2 * k * 0.01, 0.0, 0.0, 0.2)))
    odo = hist.odometry_at(1.0, 0.1)
    assert odo is not None
    np.testing.assert_allclose(odo, [0.5, 0.0, -0.1], atol=1e-6)
    # Between two samples the odometry is interpolated; outside them there is none.
    mid = hist.odometry_at(0.995, 0.1)
    assert mid is not None and mid[2] == pytest.approx(-0.099, abs=1e-6)
    assert hist.odometry_at(2.0, 0.1) is None


def test_posed_source_passes_the_odometry_pose_with_the_estimates_height_and_tilt() -> None:
    hist = SharedPoseHistory(16)
    hist.push(1.0, pose_from_xyz_rpy(5.0, 0.0, 1.2, 0.1, 0.0, 0.0), (0.0, 0.0, 0.0))
    hist.push(1.1, pose_from_xyz_rpy(6.0, 0.0, 1.2, 0.1, 0.0, 0.0), (1.0, 0.0, 0.2))
    hist.push(1.2, pose_from_xyz_rpy(7.0, 0.0, 1.2, 0.1, 0.0, 0.0))  # no odometry from here on
    src = TelemetryPosedSource(_Camera([_frame(1.05), _frame(1.15)]), hist, np.eye(4), wait_s=0.0)
    f = src.read()
    assert f is not None and f.T_odom_body is not None
    roll, pitch, yaw = rpy_from_rotation(f.T_odom_body[:3, :3])
    np.testing.assert_allclose([*f.T_odom_body[:3, 3], roll, pitch, yaw], [0.5, 0.0, 1.2, 0.1, 0.0, 0.1], atol=1e-9)
    f = src.read()  # bracketed by a sample without odometry: the frame has none
    assert f is not None and f.T_map_camera is not None and f.T_odom_body is None
