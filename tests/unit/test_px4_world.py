"""The PX4 world's heights and the SITL runner's tarball handling, without a SITL."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.px4 import FlightMode, encode_heartbeat_base_mode
from companion.sim.px4_sitl import TARBALL_ENV, Px4SitlError, sitl_available, tarball_path, unpack
from companion.sim.px4_world import FlightTimeline

_MAV = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def _msg(m: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    m.pack(_MAV)  # fills the header: the timeline reads the sender from it
    return m


def _heartbeat(mode: FlightMode, armed: bool) -> mavlink.MAVLink_message:
    return _msg(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                                  encode_heartbeat_base_mode(mode, armed), mode.custom_mode, 3, 3))


def _landed(state: int) -> mavlink.MAVLink_message:
    return _msg(mavlink.MAVLink_extended_sys_state_message(0, state))


def _local(d: float) -> mavlink.MAVLink_message:
    return _msg(mavlink.MAVLink_local_position_ned_message(0, 1.0, 2.0, d, 0.0, 0.0, 0.0))


def _home(d: float) -> mavlink.MAVLink_message:
    return _msg(mavlink.MAVLink_home_position_message(473977420, 85455940, 488000, 0.0, 0.0, d,
                                                      [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0))


def _range(cm: int) -> mavlink.MAVLink_message:
    return _msg(mavlink.MAVLink_distance_sensor_message(0, 0, 1000, cm, 0, 0, mavlink.MAV_SENSOR_ROTATION_PITCH_270, 0))


def test_height_is_above_the_floor_not_above_a_moving_home() -> None:
    tl = FlightTimeline()
    for m in (_home(0.46), _heartbeat(FlightMode.HOLD, False), _landed(mavlink.MAV_LANDED_STATE_ON_GROUND),
              _local(0.30)):
        tl.handle(m)
    assert tl.xyz_map_m == pytest.approx((2.0, 1.0, 0.0))  # the floor is where it stood, not home's 0.46
    for m in (_heartbeat(FlightMode.TAKEOFF, True), _landed(mavlink.MAV_LANDED_STATE_IN_AIR), _home(-0.97),
              _local(-0.30)):
        tl.handle(m)
    assert tl.xyz_map_m[2] == pytest.approx(0.60)  # home's jump in flight changes nothing
    assert tl.events[-1].height_above_home_m == pytest.approx(0.46 - 0.30)  # home and position at the change


def test_range_finder_sets_the_floor_when_present() -> None:
    tl = FlightTimeline()
    for m in (_heartbeat(FlightMode.HOLD, True), _landed(mavlink.MAV_LANDED_STATE_IN_AIR), _home(0.0),
              _local(-1.0), _range(80), _local(-1.1)):
        tl.handle(m)
    assert tl.range_m == pytest.approx(0.80)
    assert tl.xyz_map_m[2] == pytest.approx(0.90)  # 0.80 m measured at d=-1.0, then 0.1 m higher


def test_a_mode_change_is_dated_after_the_heartbeat_before_it() -> None:
    tl = FlightTimeline()
    tl.handle(_heartbeat(FlightMode.HOLD, True))
    hold_s = tl.events[-1].t_s
    assert tl.events[-1].after_t_s is None  # nothing reported before the first heartbeat
    tl.handle(_heartbeat(FlightMode.HOLD, True))  # unchanged: no event, but a later bound
    tl.handle(_heartbeat(FlightMode.OFFBOARD, True))
    assert tl.events[-1].mode == "OFFBOARD" and hold_s < tl.events[-1].after_t_s <= tl.events[-1].t_s
    assert len(tl.events) == 2


def test_other_senders_are_ignored() -> None:
    tl = FlightTimeline()
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    m = mavlink.MAVLink_home_position_message(0, 0, 0, 0.0, 0.0, 5.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)
    m.pack(gcs)
    tl.handle(m)
    assert tl.home_down_m is None


def _tarball(path: Path, script: bytes = b"#!/bin/sh\n") -> Path:
    with tarfile.open(path, "w:gz") as tar:
        info = tarfile.TarInfo("px4-sitl/run-sih.sh")
        info.size, info.mode = len(script), 0o755
        tar.addfile(info, io.BytesIO(script))
    return path


def test_tarball_from_the_environment_and_a_named_reason_when_missing(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(TARBALL_ENV, str(tmp_path / "none.tar.gz"))
    assert tarball_path() == tmp_path / "none.tar.gz"
    ok, why = sitl_available()
    assert not ok and str(tmp_path / "none.tar.gz") in why and TARBALL_ENV in why
    with pytest.raises(Px4SitlError, match="not found"):
        unpack(cache_dir=tmp_path / "cache")


def test_unpacked_once_per_tarball_hash(tmp_path: Path) -> None:
    a = _tarball(tmp_path / "a.tar.gz")
    first = unpack(a, tmp_path / "cache")
    assert (first / "run-sih.sh").is_file() and (first / "run-sih.sh").stat().st_mode & 0o100
    (first / "marker").write_text("kept")
    assert unpack(a, tmp_path / "cache") == first and (first / "marker").exists()  # not unpacked again
    b = _tarball(tmp_path / "b.tar.gz", b"#!/bin/sh\necho other\n")
    assert unpack(b, tmp_path / "cache") != first


def test_engage_judged_over_the_heartbeat_lag() -> None:
    from companion.sim.px4_probes import HEARTBEAT_LAG_S, engage_check
    from companion.sim.px4_world import FlightEvent

    offboard = FlightEvent(10.0, "OFFBOARD", True, "IN_AIR", (0.0, 0.0, 0.61))
    climbing = [(10.0 - HEARTBEAT_LAG_S + 0.1, 0.0, 0.0, 0.02), (10.0, 0.0, 0.0, 0.61)]
    hovering = [(10.0 - HEARTBEAT_LAG_S + 0.1, 0.0, 0.0, 0.58), (10.0, 0.0, 0.0, 0.61)]
    assert engage_check([offboard], 0.6)[0]  # the report alone looks fine
    assert not engage_check([offboard], 0.6, path=climbing)[0]  # engaged near the floor, reported late
    assert engage_check([offboard], 0.6, path=hovering)[0]
    left_over = FlightEvent(1.0, "OFFBOARD", False, "ON_GROUND", (0.0, 0.0, 0.0))
    assert engage_check([left_over, offboard], 0.6, path=hovering)[0]  # disarmed OFFBOARD is no engagement
    # A heartbeat 0.5 s before the report still said Hold: the climb before it was PX4's, not ours.
    after_hold = FlightEvent(10.0, "OFFBOARD", True, "IN_AIR", (0.0, 0.0, 0.61), after_t_s=9.5)
    assert engage_check([after_hold], 0.6, path=climbing)[0]
    sank = [(9.6, 0.0, 0.0, 0.1), (10.0, 0.0, 0.0, 0.61)]
    assert not engage_check([after_hold], 0.6, path=sank)[0]
    # Asked for OFFBOARD 0.2 s before the report: PX4 switched after that, above the floor.
    assert engage_check([after_hold], 0.6, path=sank, requests_s=[1.0, 9.8])[0]
    assert not engage_check([after_hold], 0.6, path=sank, requests_s=[9.55])[0]
