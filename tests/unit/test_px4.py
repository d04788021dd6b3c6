"""PX4 custom-mode encoding (companion.px4)."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion import px4
from companion.px4 import FlightMode


def test_known_custom_mode_words_match_px4() -> None:
    # Values as PX4 SITL reports them in HEARTBEAT.custom_mode.
    assert FlightMode.OFFBOARD.custom_mode == 393216
    assert FlightMode.HOLD.custom_mode == 50593792
    assert FlightMode.MISSION.custom_mode == 67371008
    assert FlightMode.LAND.custom_mode == 100925440
    assert FlightMode.POSCTL.custom_mode == 196608


@pytest.mark.parametrize("mode", list(FlightMode))
def test_every_mode_round_trips(mode: FlightMode) -> None:
    assert px4.decode_custom_mode(mode.custom_mode) is mode
    base = px4.encode_heartbeat_base_mode(mode, armed=True)
    decoded = px4.decode_heartbeat(base, mode.custom_mode)
    assert decoded.armed and decoded.mode is mode
    assert px4.mode_from_set_mode_params(*px4.set_mode_params(mode)) is mode


@given(st.integers(0, 255), st.integers(0, 255))
def test_split_inverts_encode(main: int, sub: int) -> None:
    assert px4.split_custom_mode(px4.encode_custom_mode(main, sub)) == (main, sub)


def test_unknown_and_non_custom_modes_decode_to_none() -> None:
    assert px4.decode_custom_mode(px4.encode_custom_mode(42, 0)) is None
    assert px4.decode_custom_mode(px4.encode_custom_mode(4, 77)) is None
    # Without the custom-mode flag the word carries no PX4 mode.
    assert px4.decode_heartbeat(px4.MAV_MODE_FLAG_SAFETY_ARMED, FlightMode.HOLD.custom_mode).mode is None
    assert px4.mode_from_set_mode_params(0.0, 4.0, 3.0) is None


def test_non_auto_main_mode_ignores_sub_mode() -> None:
    assert px4.decode_custom_mode(px4.encode_custom_mode(6, 3)) is FlightMode.OFFBOARD


def test_disarmed_heartbeat() -> None:
    base = px4.encode_heartbeat_base_mode(FlightMode.HOLD, armed=False)
    assert not px4.decode_heartbeat(base, FlightMode.HOLD.custom_mode).armed


def test_out_of_range_rejected() -> None:
    with pytest.raises(ValueError, match="out of range"):
        px4.encode_custom_mode(256, 0)


def test_map_frame_heights_are_above_home_not_the_local_origin() -> None:
    """PX4's local z is -0.86 m on the ground with GPS height: the map's z is above home."""
    import dataclasses

    from companion.mavlink.state import HomePosition, LandedState, MapFrame, VehicleState

    frame = MapFrame(floor_down_m=-0.86)
    assert frame.from_ned(1.0, 2.0, -0.86) == pytest.approx((2.0, 1.0, 0.0))
    assert frame.to_ned(2.0, 1.0, 1.0) == pytest.approx((1.0, 2.0, -1.86))
    state = VehicleState(heartbeat_age_s=0.1, armed=False, flight_mode=None, landed_state=LandedState.ON_GROUND,
                         position_ned_m=(0.0, 0.0, -0.86), velocity_ned_m_s=None, position_age_s=0.0,
                         attitude_rpy_rad=None, battery_v=None, battery_remaining=None, home=None,
                         global_position=None, autopilot_system_status=None)
    assert state.position_map_m is None and not state.ready_to_arm  # no home yet
    state = dataclasses.replace(state, home=HomePosition(47.0, 8.0, 488.0, (0.0, 0.0, -0.86)),
                                floor_down_m=-0.86)
    assert state.height_above_floor_m == pytest.approx(0.0) and state.ready_to_arm
    assert not dataclasses.replace(state, prearm_ok=False).ready_to_arm


def test_a_downward_range_sensor_must_agree_that_the_vehicle_is_high_enough() -> None:
    import dataclasses

    from companion.mavlink.state import HomePosition, LandedState, VehicleState
    from companion.service.mission_runner import took_off

    state = VehicleState(heartbeat_age_s=0.1, armed=True, flight_mode=FlightMode.HOLD, landed_state=LandedState.IN_AIR,
                         position_ned_m=(0.0, 0.0, -1.86), velocity_ned_m_s=None, position_age_s=0.0,
                         attitude_rpy_rad=None, battery_v=None, battery_remaining=None,
                         home=HomePosition(47.0, 8.0, 488.0, (0.0, 0.0, -0.86)), global_position=None,
                         autopilot_system_status=None, floor_down_m=-0.86)
    assert took_off(state, 1.0)
    # The estimate says 1 m above the floor; the range finder sees 0.2 m: not clear of it.
    assert not took_off(dataclasses.replace(state, range_down_m=0.2, range_down_age_s=0.05), 1.0)
    assert took_off(dataclasses.replace(state, range_down_m=0.2, range_down_age_s=5.0), 1.0)  # stale
    assert not took_off(dataclasses.replace(state, flight_mode=FlightMode.TAKEOFF), 1.0)


def test_the_map_frame_floor_is_where_the_vehicle_stood_landed() -> None:
    """PX4 moves home's z in flight as its height estimate drifts, and home's z need not be
    where the vehicle stands: the floor is the vehicle's own z while landed."""
    from pymavlink.dialects.v20 import common as mavlink

    from companion.mavlink.state import VehicleStateTracker

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    tracker = VehicleStateTracker()

    def feed(msg: mavlink.MAVLink_message) -> None:
        tracker.handle(mavlink.MAVLink(None).decode(bytearray(msg.pack(mav))))

    def home(z: float) -> mavlink.MAVLink_message:
        return mav.home_position_encode(473977420, 85455940, 488000, 0.0, 0.0, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    feed(home(-0.70))
    assert tracker.snapshot().map_frame.floor_down_m == pytest.approx(-0.70)  # nothing better yet
    feed(mav.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_ON_GROUND))
    feed(mav.local_position_ned_encode(0, 0.0, 0.0, -0.86, 0.0, 0.0, 0.0))
    assert tracker.snapshot().map_frame.floor_down_m == pytest.approx(-0.86)
    feed(mav.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_IN_AIR))
    feed(home(-1.20))  # moved in flight
    feed(mav.local_position_ned_encode(0, 0.0, 0.0, -1.86, 0.0, 0.0, 0.0))
    state = tracker.snapshot()
    assert state.map_frame.floor_down_m == pytest.approx(-0.86)
    assert state.height_above_floor_m == pytest.approx(1.0)


# --- parameter encoding --------------------------------------------------------------------------

def test_int32_params_travel_bytewise_as_px4_sends_them() -> None:
    # EKF2_NOAID_TOUT = 5000000 us: PX4 puts the integer's bytes in the float field.
    wire = struct.unpack("<f", struct.pack("<i", 5_000_000))[0]
    assert px4.encode_param_value(5_000_000, px4.MAV_PARAM_TYPE_INT32) == wire
    assert px4.decode_param_value(wire, px4.MAV_PARAM_TYPE_INT32) == 5_000_000
    assert px4.decode_param_value(5_000_000.0, px4.MAV_PARAM_TYPE_REAL32) == 5_000_000.0


_INT_RANGES = {
    px4.MAV_PARAM_TYPE_UINT8: (0, 2**8 - 1), px4.MAV_PARAM_TYPE_INT8: (-(2**7), 2**7 - 1),
    px4.MAV_PARAM_TYPE_UINT16: (0, 2**16 - 1), px4.MAV_PARAM_TYPE_INT16: (-(2**15), 2**15 - 1),
    px4.MAV_PARAM_TYPE_UINT32: (0, 2**32 - 1), px4.MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
}


@given(st.sampled_from(sorted(_INT_RANGES)).flatmap(
    lambda t: st.tuples(st.just(t), st.integers(*_INT_RANGES[t]))))
def test_every_integer_type_is_read_from_the_fields_low_bytes(type_value: tuple[int, int]) -> None:
    param_type, value = type_value
    wire = px4.encode_param_value(value, param_type)
    raw = struct.pack("<f", wire)
    lo, hi = _INT_RANGES[param_type]
    assert raw == (value % (hi - lo + 1)).to_bytes(4, "little") or math.isnan(wire)  # zero padded
    assert px4.decode_param_value(wire, param_type) == value or math.isnan(wire)


def test_small_integer_types_are_not_cast_by_value() -> None:
    # An INT16 of -2 is the bytes fe ff 00 00 in the field, a denormal float, not -2.0.
    wire = struct.unpack("<f", b"\xfe\xff\x00\x00")[0]
    assert px4.decode_param_value(wire, px4.MAV_PARAM_TYPE_INT16) == -2
    assert px4.decode_param_value(wire, px4.MAV_PARAM_TYPE_UINT8) == 254


def test_an_integer_out_of_its_types_range_is_refused() -> None:
    with pytest.raises(ValueError, match="MAV_PARAM_TYPE 2"):
        px4.encode_param_value(300, px4.MAV_PARAM_TYPE_INT8)


def test_param_ids_lose_their_nul_padding() -> None:
    assert px4.param_id_str(b"EKF2_NOAID_TOUT\x00") == "EKF2_NOAID_TOUT"
    assert px4.param_id_str("NAV_ACC_RAD\x00\x00\x00") == "NAV_ACC_RAD"
