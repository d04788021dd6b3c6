"""External-vision ODOMETRY: map ENU / body FLU poses converted to PX4's NED / FRD."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.mavlink.link import MavlinkLink
from companion.mavlink.vision import (
    DEFAULT_YAW_STD_RAD,
    ECHOED_HEIGHT_STD_M,
    ECHOED_TILT_STD_RAD,
    VisionPose,
    VisionStream,
    pose_covariance,
    vision_odometry_message,
)
from semmap.frames import (
    R_FLU_FRD,
    R_NED_ENU,
    make_transform,
    ned_pose_from_map,
    pose_from_xyz_rpy,
    quaternion_to_rotation,
    quaternion_wxyz_from_rotation,
    rotation_from_rpy,
)

angles = st.floats(-math.pi, math.pi)
small = st.floats(-1.2, 1.2)
coords = st.floats(-50.0, 50.0)


def test_level_vehicle_facing_north() -> None:
    # Map ENU yaw +90 deg = facing north; at map (east 1, north 2, up 3).
    p, R = ned_pose_from_map(pose_from_xyz_rpy(1.0, 2.0, 3.0, yaw_rad=math.pi / 2))
    assert p == pytest.approx([2.0, 1.0, -3.0])
    assert R == pytest.approx(np.eye(3), abs=1e-12)  # FRD aligned with NED: heading north
    assert quaternion_wxyz_from_rotation(R) == pytest.approx((1.0, 0.0, 0.0, 0.0))


@given(roll=small, pitch=small, yaw=angles, n=coords, e=coords, d=coords)
def test_round_trip_from_a_ned_attitude(roll: float, pitch: float, yaw: float, n: float, e: float, d: float) -> None:
    """A PX4 attitude (NED/FRD Euler angles) expressed as a map pose converts back exactly."""
    R_ned_frd = rotation_from_rpy(roll, pitch, yaw)
    T_map_body = make_transform(R_NED_ENU.T @ R_ned_frd @ R_FLU_FRD.T, R_NED_ENU.T @ np.array([n, e, d]))
    p, R = ned_pose_from_map(T_map_body)
    assert p == pytest.approx([n, e, d], abs=1e-9)
    assert R == pytest.approx(R_ned_frd, abs=1e-9)
    w, x, y, z = quaternion_wxyz_from_rotation(R)
    assert w >= 0.0
    assert quaternion_to_rotation(x, y, z, w) == pytest.approx(R_ned_frd, abs=1e-9)


def test_bad_pose_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        ned_pose_from_map(np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = math.nan
    with pytest.raises(ValueError, match="finite"):
        ned_pose_from_map(bad)


def test_odometry_message_fields() -> None:
    link = MavlinkLink("udpout://127.0.0.1:9")
    T = pose_from_xyz_rpy(1.0, 2.0, 0.5, yaw_rad=0.0)  # facing east
    msg = vision_odometry_message(link, T, 1234, velocity_map_m_s=np.array([1.0, 0.0, 0.0]),
                                  reset_counter=3)
    decoded = mavlink.MAVLink(None).decode(bytearray(msg.pack(link.mav)))
    assert (decoded.frame_id, decoded.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD)
    assert decoded.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert (decoded.x, decoded.y, decoded.z) == pytest.approx((2.0, 1.0, -0.5))
    # Facing east and moving east: forward speed 1 m/s in the body frame.
    assert (decoded.vx, decoded.vy, decoded.vz) == pytest.approx((1.0, 0.0, 0.0), abs=1e-6)
    assert decoded.reset_counter == 3 and decoded.time_usec == 1234
    assert math.isnan(decoded.rollspeed) and math.isnan(decoded.pose_covariance[0])
    no_vel = vision_odometry_message(link, T, 1)
    assert math.isnan(no_vel.vx)


def test_pose_covariance_carries_what_the_slam_measures() -> None:
    link = MavlinkLink("udpout://127.0.0.1:9")
    T = pose_from_xyz_rpy(1.0, 2.0, 0.5, yaw_rad=0.3)
    msg = vision_odometry_message(link, T, 1, position_std_m=0.05, yaw_std_rad=math.radians(2.0))
    cov = mavlink.MAVLink(None).decode(bytearray(msg.pack(link.mav))).pose_covariance
    # Upper triangle, row-major: x at 0, y at 6, z at 11, roll 15, pitch 18, yaw 20.
    assert cov[0] == pytest.approx(0.0025) and cov[6] == pytest.approx(0.0025)
    assert cov[20] == pytest.approx(math.radians(2.0) ** 2)
    # Height, roll and pitch are PX4's own (the SLAM echoes them): finite, and wide.
    assert cov[11] == pytest.approx(ECHOED_HEIGHT_STD_M ** 2) and cov[11] >= 100 * cov[0]
    assert cov[15] == cov[18] == pytest.approx(ECHOED_TILT_STD_RAD ** 2) and cov[15] > cov[20]
    assert all(cov[k] == 0.0 for k in range(21) if k not in (0, 6, 11, 15, 18, 20))
    assert all(math.isnan(v) for v in pose_covariance(None, 0.1))


def _ekf2_ev_variances(odom: mavlink.MAVLink_odometry_message, evp_noise_m: float,
                       eva_noise_rad: float) -> tuple[list[float], list[float]]:
    """The position and orientation variances PX4's EKF2 fuses an ODOMETRY with
    (mavlink_receiver: the covariance's diagonal; EKF2::UpdateExtVisionSample with
    EKF2_EV_NOISE_MD 0: the three taken, floored at the noise parameter, only when all three
    are finite, else the parameter for all three)."""
    c = odom.pose_covariance

    def take(var: list[float], noise: float) -> list[float]:
        if all(math.isfinite(v) for v in var):
            return [max(noise ** 2, v) for v in var]
        return [noise ** 2] * 3
    return take([c[0], c[6], c[11]], evp_noise_m), take([c[15], c[18], c[20]], eva_noise_rad)


def test_ekf2_fuses_the_variances_we_send_not_its_noise_parameters() -> None:
    link = MavlinkLink("udpout://127.0.0.1:9")
    msg = vision_odometry_message(link, pose_from_xyz_rpy(1.0, 2.0, 0.5, yaw_rad=0.3), 1,
                                  position_std_m=0.05, yaw_std_rad=math.radians(2.0))
    decoded = mavlink.MAVLink(None).decode(bytearray(msg.pack(link.mav)))
    # GPS_DENIED_PX4_PARAMS: EKF2_EVP_NOISE and EKF2_EVA_NOISE 0.02 (floors below our errors).
    pos_var, att_var = _ekf2_ev_variances(decoded, 0.02, 0.02)
    assert pos_var[:2] == pytest.approx([0.0025, 0.0025])
    assert att_var[2] == pytest.approx(math.radians(2.0) ** 2)
    # Without a yaw error the heading still gets a finite one (else EKF2 drops the attitude triple).
    no_yaw = mavlink.MAVLink(None).decode(bytearray(vision_odometry_message(
        link, np.eye(4), 1, position_std_m=0.05).pack(link.mav)))
    assert _ekf2_ev_variances(no_yaw, 0.02, 0.02)[1][2] == pytest.approx(DEFAULT_YAW_STD_RAD ** 2)


def test_vision_stream_counts_new_poses_apart_from_repeats() -> None:
    link = MavlinkLink("udpout://127.0.0.1:9")
    sent: list[mavlink.MAVLink_message] = []
    link.send = sent.append  # type: ignore[method-assign]
    poses = [VisionPose(1.0, np.eye(4)), VisionPose(1.0, np.eye(4)), VisionPose(1.1, np.eye(4), reset_counter=2,
                                                                               position_std_m=0.05)]
    stream = VisionStream(link, lambda: poses.pop(0) if poses else None, 30.0)
    assert stream.last_sent_s is None
    assert [stream.send_once() for _ in range(4)] == [True, True, True, False]
    assert (stream.sent, stream.sent_new, stream.skipped) == (3, 2, 1)
    assert stream.last_sent_s is not None and stream.last_new_s is not None
    assert sent[-1].reset_counter == 2 and sent[-1].pose_covariance[0] == pytest.approx(0.0025)


@pytest.mark.asyncio
async def test_vision_stream_outlives_a_failing_pose_source() -> None:
    # The stream is PX4's only position without GPS: a source that raises once must not end it.
    link = MavlinkLink("udpout://127.0.0.1:9")
    sent: list[mavlink.MAVLink_message] = []
    link.send = sent.append  # type: ignore[method-assign]
    calls = 0
    six_calls = asyncio.Event()

    def source() -> VisionPose:
        nonlocal calls
        calls += 1
        if calls == 6:
            six_calls.set()
        if calls == 2:
            raise RuntimeError("pose source bug")
        return VisionPose(0.01 * calls, np.eye(4))

    async with VisionStream(link, source, 200.0) as stream:
        await asyncio.wait_for(six_calls.wait(), 5.0)
    assert stream.source_errors == 1
    assert len(sent) >= 4
