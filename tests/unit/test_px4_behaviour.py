"""The mock autopilot's PX4-behaviour switches and frame helpers (no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.geo import GeoOrigin
from companion.sim.autopilot.behaviour import (
    Px4Behaviour,
    Wobble,
    accept_target,
    behaviour_from_settings,
    ekf_origin,
    report_ned,
)
from companion.sim.autopilot.vehicle import Target


def test_defaults_are_px4s_and_naive_turns_every_one_off() -> None:
    px4, naive = Px4Behaviour(), Px4Behaviour.naive()
    assert px4.floor_z_ned_m == -0.86 and px4.ready_after_s > 0 and not px4.heartbeat_on_change
    assert naive.floor_z_ned_m == 0.0 and naive.ready_after_s == 0.0 and naive.heartbeat_on_change
    assert not (naive.offboard_during_takeoff_dropped or naive.mode_after_disarm or naive.null_island_items
                or naive.offboard_loss_px4_actions or naive.tracking_delay_s or naive.wobble_m)


def test_bad_values_are_refused_with_their_name() -> None:
    with pytest.raises(ValueError, match="clock_rate"):
        Px4Behaviour(clock_rate=0.0)
    with pytest.raises(ValueError, match="wobble_m"):
        Px4Behaviour(wobble_m=-0.1)


def test_settings_parse_numbers_and_switches() -> None:
    b = behaviour_from_settings(["ready_after_s=20", "heartbeat_on_change=true", "floor_z_ned_m=1.1"])
    assert (b.ready_after_s, b.heartbeat_on_change, b.floor_z_ned_m) == (20.0, True, 1.1)
    assert behaviour_from_settings(["wobble_m=0"], Px4Behaviour.naive()).ready_after_s == 0.0
    for bad, what in (("nope=1", "NAME=VALUE"), ("ready_after_s", "NAME=VALUE"),
                      ("mode_after_disarm=maybe", "true/false"), ("clock_rate=fast", "not a number")):
        with pytest.raises(ValueError, match=what):
            behaviour_from_settings([bad])


def test_reported_frame_round_trip_and_origin() -> None:
    floor_z = -0.86
    assert report_ned((1.0, 2.0, 0.0), floor_z) == (1.0, 2.0, -0.86)
    # A setpoint 2 m above the floor, sent in the reported frame, is flown 2 m above the floor.
    target = accept_target(Target(position_ned_m=(1.0, 2.0, -2.86)), floor_z)
    assert target.position_ned_m == pytest.approx((1.0, 2.0, -2.0))
    assert accept_target(Target(velocity_ned_m_s=(0.0, 0.0, 1.0)), floor_z).position_ned_m is None
    origin = ekf_origin(GeoOrigin(47.0, 8.0, 488.0), floor_z)
    assert origin.alt_m == pytest.approx(487.14)
    assert origin.to_global(*report_ned((0.0, 0.0, -1.0), floor_z))[2] == pytest.approx(489.0)


def test_wobble_is_seeded_smooth_and_bounded() -> None:
    a, b = Wobble(0.03, seed=4), Wobble(0.03, seed=4)
    t = np.arange(0.0, 60.0, 0.01)
    xs = np.array([a.offset_ned_m(float(s)) for s in t])
    assert np.array_equal(xs[100], b.offset_ned_m(1.0))
    assert np.abs(xs[:, :2]).max() <= 0.03 + 1e-12 and np.abs(xs[:, 2]).max() <= 0.015 + 1e-12
    assert np.abs(xs[:, :2]).max() > 0.01  # it does move
    speed_m_s = np.abs(np.diff(xs, axis=0)).max() / 0.01
    assert speed_m_s < 2 * math.pi * 0.7 * 0.03  # slower than its fastest component at full amplitude
    assert not np.any(Wobble(0.0, seed=1).offset_ned_m(3.0))
