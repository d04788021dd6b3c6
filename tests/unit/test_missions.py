"""Mission files and the typed plan (companion.mission_files, companion.missions) and the
flat-earth home conversion (companion.geo)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.geo import GeoOrigin
from companion.mission_files import load_mission, parse_plan_json, parse_yaml_mission, save_mission
from companion.missions import (
    CMD_CHANGE_SPEED,
    CMD_LAND,
    CMD_RTL,
    CMD_TAKEOFF,
    CMD_WAYPOINT,
    MissionItemInt,
    MissionPlan,
    Waypoint,
    items_to_plan,
    plan_to_items,
)

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "missions"
HOME = GeoOrigin()


# --- geo ---------------------------------------------------------------------------------------

@given(st.floats(-2000, 2000), st.floats(-2000, 2000), st.floats(-100, 100),
       st.floats(-60, 60), st.floats(-179, 179))
def test_geo_round_trip(n: float, e: float, d: float, lat0: float, lon0: float) -> None:
    home = GeoOrigin(lat0, lon0, 100.0)
    back = home.to_ned(*home.to_global(n, e, d))
    assert back == pytest.approx((n, e, d), abs=1e-6)


def test_geo_scale_matches_earth() -> None:
    lat, lon, alt = HOME.to_global(111.32, 0.0, -2.0)
    assert lat - HOME.lat_deg == pytest.approx(0.001, rel=1e-3)  # ~111 m per 0.001 deg
    assert lon == HOME.lon_deg and alt == pytest.approx(HOME.alt_m + 2.0)
    with pytest.raises(ValueError, match="latitude"):
        GeoOrigin(91.0, 0.0, 0.0)


# --- YAML --------------------------------------------------------------------------------------

def test_example_square_parses() -> None:
    plan = load_mission(REPO / "config" / "missions" / "square.yaml")
    assert [w.action for w in plan.waypoints] == ["takeoff"] + ["waypoint"] * 4 + ["land"]
    assert plan.waypoints[2].xyz_map_m == (3.0, 3.0, 1.5)
    assert plan.waypoints[2].hold_s == 1.0 and plan.waypoints[1].speed_m_s == 1.0
    assert plan.home is None


def test_local_waypoints_resolve_around_home_in_map_frame() -> None:
    plan = parse_yaml_mission({"home": {"lat_deg": HOME.lat_deg, "lon_deg": HOME.lon_deg,
                                        "alt_m": HOME.alt_m},
                               "waypoints": [{"x_m": 3.0, "y_m": 4.0, "z_m": 1.5}]}, "t.yaml")
    wp = plan.resolved(None).waypoints[0]
    n, e, d = HOME.to_ned(wp.lat_deg, wp.lon_deg, HOME.alt_m - 1.5)
    # map x is east, y north
    assert (n, e) == pytest.approx((4.0, 3.0), abs=1e-6) and wp.rel_alt_m == 1.5
    assert wp.to_local(HOME).xyz_map_m == pytest.approx((3.0, 4.0, 1.5), abs=1e-6)


def test_local_waypoints_without_any_home_are_refused() -> None:
    plan = parse_yaml_mission({"waypoints": [{"x_m": 1, "y_m": 1, "z_m": 1}]}, "t.yaml")
    with pytest.raises(MissionError, match="t.yaml: local .* need a home"):
        plan.resolved(None)


@pytest.mark.parametrize(("doc", "message"), [
    ({"waypoints": [{"x_m": 1, "y_m": 2}]}, r"waypoints\[0\]: a waypoint needs an altitude"),
    ({"waypoints": [{"x_m": 1, "z_m": 2}]}, r"waypoints\[0\]: x_m and y_m go together"),
    ({"waypoints": [{"x_m": 1, "y_m": 1, "lat_deg": 47, "lon_deg": 8, "z_m": 1}]},
     r"waypoints\[0\]: give either x_m/y_m"),
    ({"waypoints": [{"action": "takeoff", "z_m": 1}, {"action": "fly", "x_m": 1, "y_m": 1}]},
     r"waypoints\[1\]\.action"),
    ({"waypoints": [{"x_m": 1, "y_m": 1, "z_m": 1, "speed": 2}]}, r"waypoints\[0\]\.speed: unknown key"),
    ({"waypoints": [{"lat_deg": 95, "lon_deg": 8, "alt_m": 1}]}, r"waypoints\[0\]\.lat_deg"),
    ({"waypoints": [{"action": "rtl", "x_m": 0, "y_m": 0}]}, r"rtl takes no position"),
    ({"waypoints": []}, r"waypoints: List should have at least 1 item"),
    ([1, 2], r"top level must be a mapping"),
])
def test_yaml_errors_name_file_and_item(doc: object, message: str) -> None:
    with pytest.raises(MissionError, match=rf"m\.yaml: .*{message}"):
        parse_yaml_mission(doc, "m.yaml")


def test_bad_files(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("waypoints: [\n", encoding="utf-8")
    with pytest.raises(MissionError, match=r"a\.yaml: not valid YAML at line"):
        load_mission(tmp_path / "a.yaml")
    (tmp_path / "b.plan").write_text("{", encoding="utf-8")
    with pytest.raises(MissionError, match=r"b\.plan: not valid JSON"):
        load_mission(tmp_path / "b.plan")
    with pytest.raises(MissionError, match="cannot read"):
        load_mission(tmp_path / "missing.yaml")
    (tmp_path / "c.txt").write_text("", encoding="utf-8")
    with pytest.raises(MissionError, match="unknown mission file type"):
        load_mission(tmp_path / "c.txt")


# --- QGroundControl .plan ----------------------------------------------------------------------

def test_qgc_plan_parses() -> None:
    plan = load_mission(DATA / "qgc_simple.plan")
    assert [w.action for w in plan.waypoints] == ["takeoff", "waypoint", "waypoint", "rtl"]
    wp = plan.waypoints[1]
    assert (wp.lat_deg, wp.lon_deg, wp.rel_alt_m) == (47.3978, 8.5457, 3.0)
    assert wp.hold_s == 2.0 and wp.acceptance_radius_m == 0.5 and wp.speed_m_s == 2.5
    assert wp.yaw_deg is None  # null in the file: face the direction of travel
    # frame 0 is AMSL: converted with plannedHomePosition
    assert plan.waypoints[2].rel_alt_m == pytest.approx(4.0) and plan.waypoints[2].yaw_deg == 90
    assert plan.home == GeoOrigin(47.397742, 8.545594, 488.0)


def _plan_with(item: dict) -> dict:
    doc = json.loads((DATA / "qgc_simple.plan").read_text(encoding="utf-8"))
    doc["mission"]["items"].insert(1, item)
    return doc


@pytest.mark.parametrize(("item", "message"), [
    ({"type": "ComplexItem", "complexItemType": "survey"}, r"ComplexItem 'survey' is not supported"),
    ({"type": "SimpleItem", "command": 2000, "frame": 2, "params": [0] * 7},
     r"unsupported command 2000 \(MAV_CMD_IMAGE_START_CAPTURE\)"),
    ({"type": "SimpleItem", "command": 16, "frame": 10, "params": [0, 0, 0, 0, 47, 8, 5]},
     r"unsupported frame 10"),
    ({"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0]},
     r"params must have 7 entries"),
    ({"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0, 0, 97, 8, 5]},
     r"latitude 97"),
    ({"type": "SimpleItem", "frame": 3, "params": [0] * 7}, r"needs integer 'command'"),
])
def test_plan_errors_name_the_item(item: dict, message: str) -> None:
    with pytest.raises(MissionError, match=rf"x\.plan: mission\.items\[1\]: {message}"):
        parse_plan_json(_plan_with(item), "x.plan")


def test_not_a_plan() -> None:
    with pytest.raises(MissionError, match="fileType must be 'Plan'"):
        parse_plan_json({"fileType": "GeoFence"}, "x.plan")


# --- MAVLink items -----------------------------------------------------------------------------

def test_items_insert_speed_changes_and_map_back() -> None:
    plan = load_mission(DATA / "qgc_simple.plan").resolved(None)
    imap = plan_to_items(plan)
    cmds = [it.command for it in imap.items]
    assert cmds == [CMD_TAKEOFF, CMD_CHANGE_SPEED, CMD_WAYPOINT, CMD_WAYPOINT, CMD_RTL]
    assert imap.waypoint_index == [0, 1, 1, 2, 3]
    assert [it.seq for it in imap.items] == list(range(5)) and imap.items[0].current == 1
    back = items_to_plan(imap.items, HOME, "vehicle")
    assert back.waypoints == plan.waypoints


def test_items_to_plan_rejects_unknown_command() -> None:
    imap = plan_to_items(MissionPlan((Waypoint("land"),), HOME, "m"))
    assert imap.items[0].command == CMD_LAND
    bad = [imap.items[0].__class__(**{**imap.items[0].__dict__, "command": 31000})]
    with pytest.raises(MissionError, match="vehicle: item 0: unsupported command 31000"):
        items_to_plan(bad, HOME, "vehicle")


def test_square_mission_never_encodes_latitude_0() -> None:
    """PX4 flies an INT item's 0/0 literally (SITL flew our square to latitude 0): take-off
    and land without a position take home's and the previous step's, as QGC does."""
    plan = load_mission(REPO / "config" / "missions" / "square.yaml").resolved(HOME)
    items = plan_to_items(plan).items
    assert all(it.x != 0 and it.y != 0 for it in items if it.command != CMD_CHANGE_SPEED)
    takeoff = next(it for it in items if it.command == CMD_TAKEOFF)
    land = next(it for it in items if it.command == CMD_LAND)
    last_wp = [it for it in items if it.command == CMD_WAYPOINT][-1]
    assert takeoff.lat_deg == pytest.approx(HOME.lat_deg, abs=1e-7)
    assert takeoff.lon_deg == pytest.approx(HOME.lon_deg, abs=1e-7)
    assert (land.x, land.y) == (last_wp.x, last_wp.y)


def test_step_without_position_and_no_home_is_an_error() -> None:
    with pytest.raises(MissionError, match=r"m: waypoint 0 \(takeoff\) has no position"):
        plan_to_items(MissionPlan((Waypoint("takeoff", rel_alt_m=1.5),), None, "m"))


_coord = st.tuples(st.floats(-30, 30), st.floats(-30, 30), st.floats(0.5, 10))


@given(st.lists(st.tuples(_coord, st.sampled_from([None, 0.5, 1.0, 2.0]),
                          st.sampled_from([0.0, 1.5]), st.sampled_from([None, 45.0])),
                min_size=1, max_size=8))
def test_local_plan_survives_items_and_back(steps: list) -> None:
    wps = tuple(Waypoint(xyz_map_m=xyz, speed_m_s=speed, hold_s=hold, yaw_deg=yaw)
                for xyz, speed, hold, yaw in steps)
    plan = MissionPlan(wps, HOME, "p").resolved(None)
    back = items_to_plan(plan_to_items(plan).items, HOME, "v")
    for orig, got in zip(wps, back.waypoints, strict=True):
        local = got.to_local(HOME)
        assert local.xyz_map_m == pytest.approx(orig.xyz_map_m, abs=0.02)  # degE7 ~ 1 cm
        assert got.hold_s == orig.hold_s and got.yaw_deg == orig.yaw_deg
    # speed carries over to later waypoints until changed, as on the vehicle
    speeds = [w.speed_m_s for w in back.waypoints]
    expected, cur = [], None
    for w in wps:
        cur = w.speed_m_s if w.speed_m_s is not None else cur
        expected.append(cur)
    assert speeds == expected


@pytest.mark.parametrize("suffix", [".plan", ".yaml"])
def test_save_and_load_round_trip(tmp_path: Path, suffix: str) -> None:
    plan = load_mission(DATA / "qgc_simple.plan").resolved(None)
    path = save_mission(plan, tmp_path / f"out{suffix}")
    again = load_mission(path)
    assert [w.action for w in again.waypoints] == [w.action for w in plan.waypoints]
    for a, b in zip(again.waypoints, plan.waypoints, strict=True):
        if math.isfinite(b.lat_deg):
            assert (a.lat_deg, a.lon_deg) == pytest.approx((b.lat_deg, b.lon_deg), abs=1e-7)
            assert a.rel_alt_m == pytest.approx(b.rel_alt_m, abs=1e-3)
        assert a.speed_m_s == b.speed_m_s and a.hold_s == b.hold_s
    assert again.home == plan.home
    with pytest.raises(MissionError, match="unknown mission file type"):
        save_mission(plan, tmp_path / "out.txt")


@pytest.mark.parametrize(("frame", "x", "y", "x_int", "y_int"), [
    (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, 47.3977421, 8.5455941, 473977421, 85455941),
    (mavlink.MAV_FRAME_LOCAL_NED, 3.25, -4.5, 32500, -45000),
])
def test_a_float_mission_item_becomes_the_one_item_type(frame: int, x: float, y: float,
                                                        x_int: int, y_int: int) -> None:
    mav = mavlink.MAVLink(None)
    legacy = mav.mission_item_encode(1, 1, 2, frame, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.5, 0.0, 0.0,
                                     x, y, 2.0)
    as_int = mav.mission_item_int_encode(1, 1, 2, frame, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.5, 0.0,
                                         0.0, x_int, y_int, 2.0)
    item = MissionItemInt.from_message(legacy)
    assert item == MissionItemInt.from_message(as_int)
    assert (item.x, item.y, item.param2, item.command_name) == (x_int, y_int, 0.5, "MAV_CMD_NAV_WAYPOINT")
