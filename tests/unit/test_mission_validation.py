"""Hostile and clumsy mission files: every non-finite or out-of-range number is an error
naming the file, the item and the field, never a 0 deg latitude (issue 33, items 3 and 7)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from companion.cli import main
from companion.errors import MissionError
from companion.mission_files import load_mission, parse_yaml_mission
from companion.mission_validation import check_plan
from companion.missions import MissionPlan, Waypoint

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "missions"


def _write_plan(tmp_path: Path, item: dict | None = None, *, home: list | None = None,
                items: list | None = None) -> Path:
    doc = json.loads((DATA / "qgc_simple.plan").read_text(encoding="utf-8"))
    if item is not None:
        doc["mission"]["items"].insert(1, item)
    if items is not None:
        doc["mission"]["items"] = items
    if home is not None:
        doc["mission"]["plannedHomePosition"] = home
    path = tmp_path / "x.plan"
    # allow_nan: json.dumps writes NaN/Infinity literals, which Python's json.loads reads back
    path.write_text(json.dumps(doc, allow_nan=True), encoding="utf-8")
    return path


def _wp(lat: object, lon: object, alt: object, p1: object = 0, p2: object = 0) -> dict:
    return {"type": "SimpleItem", "command": 16, "frame": 3, "autoContinue": True,
            "params": [p1, p2, 0, None, lat, lon, alt]}


@pytest.mark.parametrize(("item", "message"), [
    (_wp(math.nan, 8.5457, 3), r"params\[4\] is nan: not a finite number"),
    (_wp(47.3978, math.inf, 3), r"params\[5\] is inf: not a finite number"),
    (_wp(47.3978, 8.5457, -math.inf), r"params\[6\] is -inf: not a finite number"),
    (_wp(None, 8.5457, 3), r"latitude and longitude go together: one is null \(params\[4\]\)"),
    (_wp(47.3978, 8.5457, None), r"altitude is null \(params\[6\]\)"),
    (_wp(47.3978, 8.5457, -50), r"altitude above home -50 out of range .*\(params\[6\]\)"),
    (_wp(47.3978, 8.5457, 1e6), r"altitude above home 1e\+06 out of range .*\(params\[6\]\)"),
    (_wp(47.3978, 8.5457, 3, p2=-1), r"acceptance radius -1 out of range .*\(params\[1\]\)"),
    (_wp(47.3978, 8.5457, 3, p1=-5), r"hold time -5 out of range .*\(params\[0\]\)"),
    (_wp(47.3978, 200, 3), r"longitude 200 out of range .*\(params\[5\]\)"),
    (_wp(47.3978, "8.5", 3), r"params\[5\] must be a number or null"),
    (_wp(47.3978, 8.5457, True), r"params\[6\] must be a number or null"),
    ({"type": "SimpleItem", "command": 178, "frame": 2, "params": [1, 1e9, -1, 0, 0, 0, 0]},
     r"speed 1e\+09 out of range .*\(params\[1\]\)"),
    ({"type": "SimpleItem", "command": 16, "frame": 0, "params": [0, 0, 0, 0, 47.3, 8.5, 1e6]},
     r"altitude above home 999512 out of range"),
])
def test_plan_non_finite_or_out_of_range_number_names_item_and_field(
        tmp_path: Path, item: dict, message: str) -> None:
    path = _write_plan(tmp_path, item)
    with pytest.raises(MissionError, match=rf"x\.plan: mission\.items\[1\]: {message}"):
        load_mission(path)


def test_plan_nan_latitude_never_becomes_zero(tmp_path: Path) -> None:
    # The case from the issue: NaN latitude, valid longitude, uploaded as lat_deg 0.0.
    path = _write_plan(tmp_path, _wp(math.nan, 8.5457, 3))
    assert "NaN" in path.read_text(encoding="utf-8")
    with pytest.raises(MissionError, match=r"params\[4\]"):
        load_mission(path)


@pytest.mark.parametrize(("home", "message"), [
    ([math.nan, 8.5, 488], r"plannedHomePosition\[0\]: latitude nan is not a finite number"),
    ([47.3, 8.5, math.inf], r"plannedHomePosition\[2\]: altitude inf is not a finite number"),
    ([47.3, 8.5, 1e7], r"plannedHomePosition\[2\]: altitude 1e\+07 out of range"),
    ([47.3, None, 488], r"plannedHomePosition\[1\]: expected a number"),
    ([47.3, 8.5], r"plannedHomePosition: expected \[lat, lon, alt_amsl\]"),
])
def test_plan_bad_planned_home_position_is_refused(tmp_path: Path, home: list,
                                                   message: str) -> None:
    with pytest.raises(MissionError, match=rf"x\.plan: mission\.{message}"):
        load_mission(_write_plan(tmp_path, home=home))


def test_qgc_plan_with_null_home_altitude_is_accepted() -> None:
    # QGroundControl (and MAVSDK's example-mission.plan) write a null home altitude.
    plan = load_mission(DATA / "qgc_null_home_altitude.plan")
    assert [w.action for w in plan.waypoints] == ["takeoff", "waypoint", "waypoint", "rtl"]
    assert plan.home is None  # no altitude: resolved with the vehicle's home at upload
    assert plan.waypoints[1].rel_alt_m == 50.0


def test_null_home_altitude_with_an_amsl_item_names_the_item(tmp_path: Path) -> None:
    path = _write_plan(tmp_path, home=[47.3977, 8.5456, None])  # item 3 is frame 0 (AMSL)
    with pytest.raises(MissionError, match=r"mission\.items\[3\]: AMSL altitude \(frame 0\) "
                                           r"needs a plannedHomePosition with an altitude"):
        load_mission(path)


def test_plan_with_zero_items_is_refused(tmp_path: Path) -> None:
    with pytest.raises(MissionError, match=r"x\.plan: the mission has no items"):
        load_mission(_write_plan(tmp_path, items=[]))


def test_mission_check_and_upload_both_refuse_zero_items(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    path = _write_plan(tmp_path, items=[])
    assert main(["mission", "check", str(path)]) == 2
    assert "the mission has no items" in capsys.readouterr().err
    # The file is refused before any connection is tried (no autopilot on this URL).
    assert main(["mission", "upload", str(path), "--url", "udpin://127.0.0.1:9",
                 "--timeout", "0.2"]) == 2
    assert "the mission has no items" in capsys.readouterr().err


def test_mission_check_refuses_altitudes_of_minus_50_and_1e6(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    for alt in (-50, 1e6):
        path = _write_plan(tmp_path, _wp(47.3978, 8.5457, alt))
        assert main(["mission", "check", str(path)]) == 2
        assert "mission.items[1]: altitude above home" in capsys.readouterr().err


@pytest.mark.parametrize(("wp", "message"), [
    ({"x_m": math.nan, "y_m": 1.0, "z_m": 1.5}, r"waypoints\[1\]\.x_m: Input should be a finite"),
    ({"x_m": 1.0, "y_m": 1.0, "z_m": math.inf}, r"waypoints\[1\]\.z_m: Input should be a finite"),
    ({"lat_deg": 47.3, "lon_deg": math.nan, "alt_m": 2}, r"waypoints\[1\]\.lon_deg: .*finite"),
    ({"x_m": 1.0, "y_m": 1.0, "z_m": -50}, r"waypoints\[1\]\.z_m: Input should be greater"),
    ({"lat_deg": 47.3, "lon_deg": 8.5, "alt_m": 1e6}, r"waypoints\[1\]\.alt_m: Input should be less"),
    ({"x_m": 1e9, "y_m": 1.0, "z_m": 1.5}, r"waypoints\[1\]\.x_m: Input should be less"),
    ({"x_m": True, "y_m": 1.0, "z_m": 1.5}, r"waypoints\[1\]\.x_m: Input should be a valid number"),
    ({"x_m": 1.0, "y_m": 1.0, "z_m": 1.5, "acceptance_radius_m": -1},
     r"waypoints\[1\]\.acceptance_radius_m: Input should be greater"),
    ({"x_m": 1.0, "y_m": 1.0, "z_m": 1.5, "speed_m_s": math.nan},
     r"waypoints\[1\]\.speed_m_s: Input should be a finite"),
])
def test_yaml_non_finite_or_out_of_range_number_names_item_and_field(wp: dict,
                                                                     message: str) -> None:
    doc = {"waypoints": [{"action": "takeoff", "z_m": 1.5}, wp]}
    with pytest.raises(MissionError, match=rf"m\.yaml: {message}"):
        parse_yaml_mission(doc, "m.yaml")


def test_yaml_nan_from_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    path.write_text("waypoints:\n  - {action: takeoff, z_m: 1.5}\n"
                    "  - {x_m: .nan, y_m: 1.0, z_m: 1.5}\n", encoding="utf-8")
    with pytest.raises(MissionError, match=r"m\.yaml: waypoints\[1\]\.x_m"):
        load_mission(path)


def test_resolved_plan_is_checked_before_upload() -> None:
    # What upload checks after resolving: a waypoint without a finite latitude is refused.
    plan = MissionPlan((Waypoint("waypoint", math.nan, 8.5, 2.0),), None, "p")
    with pytest.raises(MissionError, match=r"p: waypoint 0 \(waypoint\): latitude nan"):
        check_plan(plan)
    ok = MissionPlan((Waypoint("takeoff", rel_alt_m=2.0), Waypoint("land", rel_alt_m=0.0)))
    assert check_plan(ok) is ok


def test_mission_check_checks_local_waypoints_resolved_like_upload(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    # 9 km north of a home at 89.95 deg is past the pole: upload would send latitude > 90.
    path = tmp_path / "polar.yaml"
    path.write_text("home: {lat_deg: 89.95, lon_deg: 0.0, alt_m: 10.0}\n"
                    "waypoints:\n  - {action: takeoff, z_m: 2}\n  - {x_m: 0, y_m: 9000, z_m: 2}\n",
                    encoding="utf-8")
    assert main(["mission", "check", str(path)]) == 2
    assert "polar.yaml: waypoint 1 (waypoint): latitude 90.03" in capsys.readouterr().err
