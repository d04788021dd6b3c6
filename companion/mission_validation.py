"""Sanity checks for mission files: every number finite and in range, or an error naming it.

One owner for what a mission may contain, shared by ``mission check``, ``mission upload`` and
the parsers in :mod:`companion.mission_files`: a NaN, an infinity or an out-of-range number is a
:class:`~companion.errors.MissionError` naming the file, the item and the field, never a
0 deg latitude.
"""

from __future__ import annotations

import math
from typing import Any

from companion.errors import MissionError
from companion.geo import GeoOrigin
from companion.missions import (
    CMD_CHANGE_SPEED,
    CMD_LAND,
    CMD_LOITER_TIME,
    CMD_TAKEOFF,
    CMD_WAYPOINT,
    FRAME_GLOBAL,
    FRAME_GLOBAL_INT,
    MissionPlan,
)

_NAN = math.nan

#: Sanity bounds, not airspace rules (the service enforces ``planner.max_altitude_m`` in flight):
#: a number outside them is a typo or a hostile file, never something to fly.
REL_ALT_RANGE_M = (-20.0, 1000.0)  # waypoint altitude above home
HOME_ALT_RANGE_M = (-500.0, 9000.0)  # home altitude AMSL
LOCAL_RANGE_M = 10_000.0  # |x_m|, |y_m| of map-frame waypoints (flat-earth conversion)
SPEED_MAX_M_S = 100.0
YAW_RANGE_DEG = (-360.0, 360.0)
_POSITION_CMDS = (CMD_WAYPOINT, CMD_LOITER_TIME, CMD_TAKEOFF, CMD_LAND)


def _range_error(what: str, value: float, lo: float, hi: float) -> str | None:
    if not math.isfinite(value):
        return f"{what} {value} is not a finite number"
    if not lo <= value <= hi:
        return f"{what} {value:g} out of range [{lo:g}, {hi:g}]"
    return None


def plan_home(php: Any, source: str) -> GeoOrigin | None:
    """``plannedHomePosition`` [lat, lon, alt_amsl]; None if absent or its altitude is null.

    QGroundControl writes a null altitude when it has no terrain height; such a home cannot
    convert AMSL altitudes, so the plan then uses the vehicle's home.
    """
    where = f"{source}: mission.plannedHomePosition"
    if php is None:
        return None
    if not isinstance(php, list) or len(php) != 3:
        raise MissionError(f"{where}: expected [lat, lon, alt_amsl] (got {php!r})")
    for k, v in enumerate(php):
        if not (v is None and k == 2) and (isinstance(v, bool) or not isinstance(v, int | float)):
            raise MissionError(f"{where}[{k}]: expected a number (got {v!r})")
    for k, name, lo, hi in ((0, "latitude", -90.0, 90.0), (1, "longitude", -180.0, 180.0),
                            (2, "altitude", *HOME_ALT_RANGE_M)):
        if php[k] is not None and (err := _range_error(name, float(php[k]), lo, hi)):
            raise MissionError(f"{where}[{k}]: {err}")
    if php[2] is None:
        return None
    return GeoOrigin(float(php[0]), float(php[1]), float(php[2]))


def _params(raw: Any, where: str) -> list[float]:
    """An item's ``params``: numbers, or null for "unset" (NaN); NaN/Infinity literals refused."""
    if not isinstance(raw, list):
        raise MissionError(f"{where}: params must be a list of 7 numbers (got {raw!r})")
    out = []
    for k, v in enumerate(raw):
        if v is None:
            out.append(_NAN)
            continue
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise MissionError(f"{where}: params[{k}] must be a number or null (got {v!r})")
        if not math.isfinite(v):
            raise MissionError(f"{where}: params[{k}] is {v}: not a finite number "
                               "(write null for an unset parameter)")
        out.append(float(v))
    return out


def _check_plan_item(cmd: int, frame: int, params: list[float], home: GeoOrigin | None,
                     where: str) -> None:
    """Refuse a ``.plan`` item whose numbers are out of range, naming the field."""
    def fail(err: str | None, k: int) -> None:
        if err:
            raise MissionError(f"{where}: {err} (params[{k}])")

    if cmd == CMD_CHANGE_SPEED:
        if math.isfinite(params[1]) and params[1] > 0:  # -1 or 0: no change (MAVLink)
            fail(_range_error("speed", params[1], 0.0, SPEED_MAX_M_S), 1)
        return
    if cmd not in _POSITION_CMDS:
        return  # unsupported commands are refused by items_to_plan, RTL has no numbers
    lat, lon, alt = params[4], params[5], params[6]
    if math.isfinite(lat) != math.isfinite(lon):
        k = 4 if not math.isfinite(lat) else 5
        raise MissionError(f"{where}: latitude and longitude go together: one is null "
                           f"(params[{k}])")
    if math.isfinite(lat):
        fail(_range_error("latitude", lat, -90.0, 90.0), 4)
        fail(_range_error("longitude", lon, -180.0, 180.0), 5)
    if math.isfinite(params[3]):
        fail(_range_error("yaw", params[3], *YAW_RANGE_DEG), 3)
    if cmd in (CMD_WAYPOINT, CMD_LOITER_TIME):
        if math.isfinite(params[0]):
            fail(_range_error("hold time", params[0], 0.0, math.inf), 0)
    if cmd == CMD_WAYPOINT and math.isfinite(params[1]):
        fail(_range_error("acceptance radius", params[1], 0.0, math.inf), 1)
    if cmd == CMD_LAND:
        return  # a landing's altitude is ignored
    if not math.isfinite(alt):
        raise MissionError(f"{where}: altitude is null (params[6])")
    if frame in (FRAME_GLOBAL, FRAME_GLOBAL_INT):
        if home is None:
            raise MissionError(f"{where}: AMSL altitude (frame {frame}) needs a "
                               "plannedHomePosition with an altitude (params[6])")
        alt -= home.alt_m
    fail(_range_error("altitude above home", alt, *REL_ALT_RANGE_M), 6)


def check_plan(plan: MissionPlan) -> MissionPlan:
    """``plan`` itself if every number in it is finite and in range, else MissionError.

    Run after parsing and again on the resolved plan before upload, where local waypoints
    have become latitudes and longitudes. An empty plan is refused: it would upload nothing.
    """
    if not plan.waypoints:
        raise MissionError(f"{plan.source}: the mission has no items")
    for i, w in enumerate(plan.waypoints):
        where = f"{plan.source}: waypoint {i} ({w.action})"
        alt_m = w.xyz_map_m[2] if w.xyz_map_m is not None else w.rel_alt_m
        errs = [_range_error("altitude above home", alt_m, *REL_ALT_RANGE_M)
                if w.action in ("waypoint", "takeoff") else None]
        if w.xyz_map_m is not None:
            errs += [_range_error(n, v, -LOCAL_RANGE_M, LOCAL_RANGE_M)
                     for n, v in zip(("x_m", "y_m"), w.xyz_map_m[:2], strict=True)]
        elif w.action == "waypoint" or math.isfinite(w.lat_deg) or math.isfinite(w.lon_deg):
            errs += [_range_error("latitude", w.lat_deg, -90.0, 90.0),
                     _range_error("longitude", w.lon_deg, -180.0, 180.0)]
        if w.speed_m_s is not None:
            errs.append(_range_error("speed", w.speed_m_s, 1e-9, SPEED_MAX_M_S))
        if w.acceptance_radius_m is not None:
            errs.append(_range_error("acceptance radius", w.acceptance_radius_m, 0.0, math.inf))
        if w.yaw_deg is not None:
            errs.append(_range_error("yaw", w.yaw_deg, *YAW_RANGE_DEG))
        errs.append(_range_error("hold time", w.hold_s, 0.0, math.inf))
        for err in errs:
            if err:
                raise MissionError(f"{where}: {err}")
    return plan


def plan_item_params(raw: Any, command: int, frame: int, home: GeoOrigin | None,
                     where: str) -> list[float]:
    """A ``.plan`` item's params as floats (null = NaN, "unset"), each checked for range.

    Raises MissionError naming ``where`` and the param; a wrong count is the caller's to name.
    """
    params = _params(raw, where)
    if len(params) == 7:
        _check_plan_item(command, frame, params, home, where)
    return params
