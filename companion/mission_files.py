"""Mission files: QGroundControl ``.plan`` and our YAML waypoint list, as one typed plan
(:class:`~companion.missions.MissionPlan`).

Two input formats, one :class:`MissionPlan`:

* **QGroundControl ``.plan``** (JSON, ``fileType: Plan``). ``SimpleItem`` entries with the
  commands NAV_WAYPOINT (16), NAV_LOITER_TIME (19), NAV_RETURN_TO_LAUNCH (20), NAV_LAND (21),
  NAV_TAKEOFF (22) and DO_CHANGE_SPEED (178) in the frames GLOBAL (0, AMSL, converted with
  ``plannedHomePosition``) or GLOBAL_RELATIVE_ALT (3). Survey/corridor/structure
  ``ComplexItem`` entries and other commands are rejected with the item's index.
* **YAML waypoint list**::

      home: {lat_deg: 47.397742, lon_deg: 8.545594, alt_m: 488.0}  # optional, see below
      speed_m_s: 1.0                                # default horizontal speed (optional)
      waypoints:
        - {action: takeoff, z_m: 1.5}
        - {x_m: 2.0, y_m: 1.0, z_m: 1.5, hold_s: 2}  # map frame: x east, y north, z up
        - {lat_deg: 47.39776, lon_deg: 8.54562, alt_m: 1.5, speed_m_s: 0.5}
        - {action: land}                            # or {action: rtl}

  A waypoint is either local (``x_m``/``y_m``/``z_m`` in the map frame, whose origin is the
  vehicle's home = PX4's local NED origin) or global (``lat_deg``/``lon_deg`` and ``alt_m``
  above home). Local waypoints are converted with the file's ``home`` if given, otherwise with
  the home position the vehicle reports at upload time.

Errors are :class:`~companion.errors.MissionError` naming the file and the item, e.g.
``plans/a.plan: mission.items[3]: unsupported command 2000 (MAV_CMD_IMAGE_START_CAPTURE)``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.geo import GeoOrigin
from companion.mission_validation import (
    HOME_ALT_RANGE_M,
    LOCAL_RANGE_M,
    REL_ALT_RANGE_M,
    SPEED_MAX_M_S,
    YAW_RANGE_DEG,
    check_plan,
    plan_home,
    plan_item_params,
)
from companion.missions import (
    FRAME_GLOBAL_REL,
    FRAME_GLOBAL_REL_INT,
    Action,
    MissionItemInt,
    MissionPlan,
    Waypoint,
    items_to_plan,
    plan_to_items,
)

_NAN = math.nan


# --- QGroundControl .plan ---------------------------------------------------------------------

def parse_plan_json(data: Any, source: str) -> MissionPlan:
    """A :class:`MissionPlan` from a decoded QGroundControl ``.plan`` document."""
    if not isinstance(data, dict) or data.get("fileType") != "Plan":
        raise MissionError(f"{source}: not a QGroundControl plan (fileType must be 'Plan')")
    mission = data.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise MissionError(f"{source}: mission.items: missing or not a list")
    home = plan_home(mission.get("plannedHomePosition"), source)
    items: list[MissionItemInt] = []
    for i, raw in enumerate(mission["items"]):
        where = f"{source}: mission.items[{i}]"
        if not isinstance(raw, dict):
            raise MissionError(f"{where}: not an object")
        if raw.get("type") != "SimpleItem":
            kind = raw.get("complexItemType", raw.get("type"))
            raise MissionError(f"{where}: {raw.get('type')} {kind!r} is not supported "
                               "(only SimpleItem)")
        try:
            cmd = int(raw["command"])
            frame = int(raw["frame"])
            params = plan_item_params(raw["params"], cmd, frame, home, where)
        except (KeyError, TypeError, ValueError) as exc:
            raise MissionError(f"{where}: needs integer 'command', 'frame' and 7 numeric "
                               f"'params' ({exc!r})") from exc
        if len(params) != 7:
            raise MissionError(f"{where}: params must have 7 entries (got {len(params)})")
        lat, lon = params[4], params[5]
        x = int(round(lat * 1e7)) if math.isfinite(lat) else 0
        y = int(round(lon * 1e7)) if math.isfinite(lon) else 0
        items.append(MissionItemInt(i, frame, cmd, 0, int(bool(raw.get("autoContinue", True))),
                                    params[0], params[1], params[2], params[3], x, y, params[6]))
    return check_plan(items_to_plan(items, home, source, label="mission.items[{i}]"))


def plan_to_json(plan: MissionPlan) -> dict[str, Any]:
    """A QGroundControl ``.plan`` document for a resolved plan."""
    home = plan.home or GeoOrigin()
    items_out = []
    for i, it in enumerate(plan_to_items(plan).items):
        frame = FRAME_GLOBAL_REL if it.frame == FRAME_GLOBAL_REL_INT else it.frame
        has_pos = it.x != 0 or it.y != 0
        params = [it.param1, it.param2, it.param3, it.param4,
                  it.lat_deg if has_pos else 0.0, it.lon_deg if has_pos else 0.0, it.z]
        items_out.append({
            "type": "SimpleItem", "command": it.command, "frame": frame,
            "params": [None if isinstance(p, float) and math.isnan(p) else p for p in params],
            "autoContinue": True, "doJumpId": i + 1,
        })
    return {
        "fileType": "Plan", "version": 1, "groundStation": "companion",
        "mission": {
            "version": 2, "firmwareType": mavlink.MAV_AUTOPILOT_PX4,
            "vehicleType": mavlink.MAV_TYPE_QUADROTOR, "cruiseSpeed": 5, "hoverSpeed": 5,
            "plannedHomePosition": [home.lat_deg, home.lon_deg, home.alt_m],
            "items": items_out,
        },
        "geoFence": {"version": 2, "circles": [], "polygons": []},
        "rallyPoints": {"version": 2, "points": []},
    }


# --- YAML waypoint list -----------------------------------------------------------------------

class _Strict(BaseModel):
    # strict: `true` is not 1.0 and "1.5" is not a number; NaN and infinity are refused
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class _YamlHome(_Strict):
    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    alt_m: float = Field(ge=HOME_ALT_RANGE_M[0], le=HOME_ALT_RANGE_M[1])


class _YamlWaypoint(_Strict):
    action: Action = "waypoint"
    x_m: float | None = Field(default=None, ge=-LOCAL_RANGE_M, le=LOCAL_RANGE_M)
    y_m: float | None = Field(default=None, ge=-LOCAL_RANGE_M, le=LOCAL_RANGE_M)
    z_m: float | None = Field(default=None, ge=REL_ALT_RANGE_M[0], le=REL_ALT_RANGE_M[1])
    lat_deg: float | None = Field(default=None, ge=-90, le=90)
    lon_deg: float | None = Field(default=None, ge=-180, le=180)
    alt_m: float | None = Field(default=None, ge=REL_ALT_RANGE_M[0], le=REL_ALT_RANGE_M[1])
    speed_m_s: float | None = Field(default=None, gt=0, le=SPEED_MAX_M_S)
    hold_s: float = Field(default=0.0, ge=0)
    acceptance_radius_m: float | None = Field(default=None, gt=0)
    yaw_deg: float | None = Field(default=None, ge=YAW_RANGE_DEG[0], le=YAW_RANGE_DEG[1])

    @model_validator(mode="after")
    def _position(self) -> _YamlWaypoint:
        local = self.x_m is not None or self.y_m is not None
        glob = self.lat_deg is not None or self.lon_deg is not None
        if local and glob:
            raise ValueError("give either x_m/y_m (map frame) or lat_deg/lon_deg, not both")
        if local and (self.x_m is None or self.y_m is None):
            raise ValueError("x_m and y_m go together")
        if glob and (self.lat_deg is None or self.lon_deg is None):
            raise ValueError("lat_deg and lon_deg go together")
        if self.z_m is not None and self.alt_m is not None:
            raise ValueError("give either z_m or alt_m, not both")
        if self.action == "waypoint":
            if not (local or glob):
                raise ValueError("a waypoint needs x_m/y_m or lat_deg/lon_deg")
            if self.z_m is None and self.alt_m is None:
                raise ValueError("a waypoint needs an altitude (z_m or alt_m, metres above home)")
        if self.action == "takeoff" and self.z_m is None and self.alt_m is None:
            raise ValueError("takeoff needs an altitude (z_m or alt_m)")
        if self.action == "rtl" and (local or glob):
            raise ValueError("rtl takes no position")
        return self


class _YamlMission(_Strict):
    home: _YamlHome | None = None
    speed_m_s: float | None = Field(default=None, gt=0, le=SPEED_MAX_M_S)
    waypoints: list[_YamlWaypoint] = Field(min_length=1)


def parse_yaml_mission(data: Any, source: str) -> MissionPlan:
    """A :class:`MissionPlan` from a decoded YAML waypoint-list document."""
    if not isinstance(data, dict):
        raise MissionError(f"{source}: top level must be a mapping with 'waypoints'")
    try:
        doc = _YamlMission.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(f"[{p}]" if isinstance(p, int) else str(p) for p in err["loc"])
            loc = loc.replace(".[", "[")
            msg = err["msg"].removeprefix("Value error, ")
            if err["type"] == "extra_forbidden":
                msg = "unknown key"
            lines.append(f"{source}: {loc or '(root)'}: {msg}")
        raise MissionError("\n".join(lines)) from exc
    home = GeoOrigin(doc.home.lat_deg, doc.home.lon_deg, doc.home.alt_m) if doc.home else None
    wps = []
    for w in doc.waypoints:
        alt = w.z_m if w.z_m is not None else w.alt_m
        alt = _NAN if alt is None else alt
        if w.action == "land":
            alt = 0.0
        common: dict[str, Any] = {
            "action": w.action, "speed_m_s": w.speed_m_s or doc.speed_m_s, "hold_s": w.hold_s,
            "acceptance_radius_m": w.acceptance_radius_m, "yaw_deg": w.yaw_deg}
        if w.x_m is not None and w.y_m is not None:
            wps.append(Waypoint(xyz_map_m=(w.x_m, w.y_m, alt), **common))
        elif w.lat_deg is not None and w.lon_deg is not None:
            wps.append(Waypoint(lat_deg=w.lat_deg, lon_deg=w.lon_deg, rel_alt_m=alt, **common))
        else:
            wps.append(Waypoint(rel_alt_m=alt, **common))
    return check_plan(MissionPlan(tuple(wps), home, source))


def plan_to_yaml_doc(plan: MissionPlan) -> dict[str, Any]:
    """The YAML document (global waypoints) for a plan."""
    out: list[dict[str, Any]] = []
    for w in plan.waypoints:
        d: dict[str, Any] = {"action": w.action}
        if w.xyz_map_m is not None:
            d.update(x_m=w.xyz_map_m[0], y_m=w.xyz_map_m[1], z_m=w.xyz_map_m[2])
        elif math.isfinite(w.lat_deg):
            d.update(lat_deg=round(w.lat_deg, 7), lon_deg=round(w.lon_deg, 7))
        if w.action in ("waypoint", "takeoff") and w.xyz_map_m is None:
            d["alt_m"] = round(w.rel_alt_m, 3)
        if w.speed_m_s is not None:
            d["speed_m_s"] = w.speed_m_s
        if w.hold_s:
            d["hold_s"] = w.hold_s
        if w.acceptance_radius_m is not None:
            d["acceptance_radius_m"] = w.acceptance_radius_m
        if w.yaw_deg is not None:
            d["yaw_deg"] = w.yaw_deg
        out.append(d)
    doc: dict[str, Any] = {}
    if plan.home is not None:
        doc["home"] = {"lat_deg": plan.home.lat_deg, "lon_deg": plan.home.lon_deg,
                       "alt_m": plan.home.alt_m}
    doc["waypoints"] = out
    return doc


# --- files ------------------------------------------------------------------------------------

def load_mission(path: str | Path) -> MissionPlan:
    """Read a ``.plan`` (JSON) or ``.yaml``/``.yml`` mission file. Raises MissionError."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"{p}: cannot read mission file: {exc.strerror or exc}") from exc
    if p.suffix.lower() == ".plan":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MissionError(f"{p}: not valid JSON at line {exc.lineno}, column {exc.colno}: "
                               f"{exc.msg}") from exc
        return parse_plan_json(data, str(p))
    if p.suffix.lower() in (".yaml", ".yml"):
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            raise MissionError(f"{p}: not valid YAML{where}") from exc
        return parse_yaml_mission(data, str(p))
    raise MissionError(f"{p}: unknown mission file type {p.suffix!r} (use .plan, .yaml or .yml)")


def save_mission(plan: MissionPlan, path: str | Path) -> Path:
    """Write ``plan`` as ``.plan`` JSON or YAML, chosen by the file suffix."""
    p = Path(path)
    if p.suffix.lower() == ".plan":
        text = json.dumps(plan_to_json(plan), indent=2) + "\n"
    elif p.suffix.lower() in (".yaml", ".yml"):
        text = yaml.safe_dump(plan_to_yaml_doc(plan), sort_keys=False)
    else:
        raise MissionError(f"{p}: unknown mission file type {p.suffix!r} (use .plan or .yaml)")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"{p}: cannot write mission file: {exc.strerror or exc}") from exc
    return p
