"""Every frame and rotation conversion in semmap.frames against its inverse (Hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from semmap.frames import (
    R_FLU_FRD,
    R_NED_ENU,
    enu_to_ned,
    map_pose_from_ned,
    ned_pose_from_map,
    ned_to_enu,
    pose_from_xyz_rpy,
    quaternion_wxyz_from_rotation,
    quaternion_wxyz_from_rpy,
    rotation_from_quaternion_wxyz,
    rotation_from_rpy,
    rpy_from_rotation,
    wrap_angle_rad,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)

coords_m = st.floats(-1e4, 1e4)
angles_rad = st.floats(-math.pi, math.pi)
#: Roll and pitch away from the Euler singularity at +-90 deg pitch.
tilts_rad = st.floats(-1.4, 1.4)
any_angle_rad = st.floats(-1e3, 1e3)
unit_quaternions = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: sum(c * c for c in q) > 1e-3)


def _same_angle(a_rad: float, b_rad: float) -> bool:
    return abs(math.remainder(a_rad - b_rad, math.tau)) < 1e-9


@given(coords_m, coords_m, coords_m)
def test_ned_enu_positions_round_trip(x: float, y: float, z: float) -> None:
    assert ned_to_enu(*enu_to_ned(x, y, z)) == (x, y, z)
    assert enu_to_ned(*ned_to_enu(x, y, z)) == (x, y, z)
    np.testing.assert_array_equal(R_NED_ENU @ np.array([x, y, z]), enu_to_ned(x, y, z))


def test_ned_enu_axes() -> None:
    # East 1, north 2, up 3 is north 2, east 1, down -3.
    assert enu_to_ned(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)


@given(angles_rad)
def test_ned_enu_yaw_round_trip(yaw_rad: float) -> None:
    assert _same_angle(yaw_ned_to_enu(yaw_enu_to_ned(yaw_rad)), yaw_rad)
    assert _same_angle(yaw_enu_to_ned(yaw_ned_to_enu(yaw_rad)), yaw_rad)


def test_ned_enu_yaw_headings() -> None:
    assert yaw_ned_to_enu(0.0) == pytest.approx(math.pi / 2)  # facing north
    assert yaw_ned_to_enu(math.pi / 2) == pytest.approx(0.0)  # facing east


@given(coords_m, coords_m, coords_m)
def test_frd_flu_round_trip(x: float, y: float, z: float) -> None:
    v = np.array([x, y, z])
    np.testing.assert_array_equal(R_FLU_FRD @ (R_FLU_FRD @ v), v)
    np.testing.assert_array_equal(R_FLU_FRD @ v, [x, -y, -z])


def test_both_axis_swaps_are_proper_rotations() -> None:
    for R in (R_NED_ENU, R_FLU_FRD):
        np.testing.assert_array_equal(R @ R, np.eye(3))
        np.testing.assert_array_equal(R.T, R)
        assert np.linalg.det(R) == pytest.approx(1.0)  # right-handed to right-handed


@given(tilts_rad, tilts_rad, angles_rad, coords_m, coords_m, coords_m)
def test_map_pose_and_ned_pose_round_trip(roll: float, pitch: float, yaw: float, x: float, y: float, z: float) -> None:
    T_map_body = pose_from_xyz_rpy(x, y, z, roll, pitch, yaw)
    p_ned, R_ned_frd = ned_pose_from_map(T_map_body)
    np.testing.assert_allclose(np.linalg.det(R_ned_frd), 1.0, atol=1e-9)
    back = map_pose_from_ned((float(p_ned[0]), float(p_ned[1]), float(p_ned[2])), rpy_from_rotation(R_ned_frd))
    np.testing.assert_allclose(back, T_map_body, atol=1e-6)


@given(tilts_rad, tilts_rad, angles_rad)
def test_quaternion_and_rotation_round_trip(roll: float, pitch: float, yaw: float) -> None:
    R = rotation_from_rpy(roll, pitch, yaw)
    q = quaternion_wxyz_from_rotation(R)
    assert q[0] >= 0.0
    assert sum(c * c for c in q) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation_from_quaternion_wxyz(q), R, atol=1e-9)


@given(unit_quaternions)
def test_rotation_and_quaternion_round_trip(q_raw: tuple[float, float, float, float]) -> None:
    n = math.sqrt(sum(c * c for c in q_raw))
    q = tuple(c / n for c in q_raw)
    back = np.array(quaternion_wxyz_from_rotation(rotation_from_quaternion_wxyz(q)))  # type: ignore[arg-type]
    assert back[0] >= 0.0
    # q and -q are the same rotation.
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-7


@given(tilts_rad, tilts_rad, angles_rad)
def test_quaternion_from_euler_angles_matches_the_matrix(roll: float, pitch: float, yaw: float) -> None:
    q = quaternion_wxyz_from_rpy(roll, pitch, yaw)
    np.testing.assert_allclose(rotation_from_quaternion_wxyz(q), rotation_from_rpy(roll, pitch, yaw), atol=1e-9)


@given(any_angle_rad)
def test_angle_wrap_lands_in_range_and_keeps_the_angle(angle_rad: float) -> None:
    w = wrap_angle_rad(angle_rad)
    assert -math.pi <= w <= math.pi
    assert _same_angle(w, angle_rad)
    assert _same_angle(wrap_angle_rad(w), w)


@given(st.lists(any_angle_rad, min_size=1, max_size=20))
def test_angle_wrap_of_an_array_is_element_wise(angles: list[float]) -> None:
    a = np.array(angles)
    np.testing.assert_allclose(wrap_angle_rad(a), [wrap_angle_rad(x) for x in angles], atol=0.0)
