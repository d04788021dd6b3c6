"""The mission as one typed plan, and its MAVLink mission items.

:class:`MissionPlan` is what a mission file (:mod:`companion.mission_files`) or the autopilot's
mission becomes: :class:`Waypoint` entries, each local (map frame: x east, y north, z up;
origin the vehicle's home = PX4's local NED origin) or global (``lat_deg``/``lon_deg``, altitude
above home). :func:`plan_to_items` and :func:`items_to_plan` convert it to and from the
``MISSION_ITEM_INT`` list an autopilot stores (NAV_WAYPOINT, NAV_LOITER_TIME,
NAV_RETURN_TO_LAUNCH, NAV_LAND, NAV_TAKEOFF, DO_CHANGE_SPEED).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.geo import GeoOrigin
from semmap.frames import enu_to_ned, ned_to_enu

Action = Literal["waypoint", "takeoff", "land", "rtl"]

CMD_WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
CMD_LOITER_TIME = mavlink.MAV_CMD_NAV_LOITER_TIME
CMD_RTL = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
CMD_LAND = mavlink.MAV_CMD_NAV_LAND
CMD_TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
CMD_CHANGE_SPEED = mavlink.MAV_CMD_DO_CHANGE_SPEED
FRAME_GLOBAL = mavlink.MAV_FRAME_GLOBAL
FRAME_GLOBAL_REL = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT
FRAME_GLOBAL_REL_INT = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
FRAME_GLOBAL_INT = mavlink.MAV_FRAME_GLOBAL_INT
FRAME_MISSION = mavlink.MAV_FRAME_MISSION
FRAME_LOCAL_NED = mavlink.MAV_FRAME_LOCAL_NED
#: Frames whose x/y are latitude/longitude (degE7 in an INT item).
GLOBAL_FRAMES = frozenset({
    FRAME_GLOBAL, FRAME_GLOBAL_INT, FRAME_GLOBAL_REL, FRAME_GLOBAL_REL_INT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
})
#: An INT item's x/y in a global frame are degrees times this, in other frames metres times ``LOCAL_SCALE``.
DEG_E7 = 1e7
LOCAL_SCALE = 1e4

_ACTION_CMD = {"waypoint": CMD_WAYPOINT, "takeoff": CMD_TAKEOFF, "land": CMD_LAND,
               "rtl": CMD_RTL}
_NAN = math.nan


@dataclass(frozen=True)
class Waypoint:
    """One mission step.

    Position is global (``lat_deg``/``lon_deg`` WGS-84, ``rel_alt_m`` above home) or local
    (``xyz_map_m``: map frame ENU metres, origin = home); :meth:`to_global` resolves local
    ones. NaN lat/lon on ``takeoff``/``land`` means "where the vehicle is"; ``rtl`` has no
    position. ``yaw_deg`` None lets the autopilot face the direction of travel.
    """

    action: Action = "waypoint"
    lat_deg: float = _NAN
    lon_deg: float = _NAN
    rel_alt_m: float = _NAN
    xyz_map_m: tuple[float, float, float] | None = None
    speed_m_s: float | None = None
    hold_s: float = 0.0
    acceptance_radius_m: float | None = None
    yaw_deg: float | None = None

    @property
    def is_local(self) -> bool:
        return self.xyz_map_m is not None

    def to_global(self, home: GeoOrigin) -> Waypoint:
        """This waypoint with a local position converted to lat/lon around ``home``."""
        if self.xyz_map_m is None:
            return self
        n, e, d = enu_to_ned(*self.xyz_map_m)
        lat, lon, _alt = home.to_global(n, e, d)
        return replace(self, lat_deg=lat, lon_deg=lon, rel_alt_m=-d, xyz_map_m=None)

    def to_local(self, home: GeoOrigin) -> Waypoint:
        """This waypoint with lat/lon converted to map-frame metres around ``home``."""
        if self.xyz_map_m is not None or not math.isfinite(self.lat_deg):
            return self
        n, e, _d = home.to_ned(self.lat_deg, self.lon_deg, home.alt_m)
        x, y, _ = ned_to_enu(n, e, 0.0)
        return replace(self, xyz_map_m=(x, y, self.rel_alt_m), lat_deg=_NAN, lon_deg=_NAN)


@dataclass(frozen=True)
class MissionPlan:
    """A parsed mission: waypoints in order, the home they refer to (if known), the source."""

    waypoints: tuple[Waypoint, ...]
    home: GeoOrigin | None = None
    source: str = "<memory>"

    def resolved(self, vehicle_home: GeoOrigin | None) -> MissionPlan:
        """All waypoints global, using the plan's home or else ``vehicle_home``."""
        home = self.home or vehicle_home
        if any(w.is_local for w in self.waypoints):
            if home is None:
                raise MissionError(f"{self.source}: local (x_m/y_m) waypoints need a home "
                                   "position: give 'home' in the file or connect to a vehicle")
        wps = tuple(w.to_global(home) if home is not None else w for w in self.waypoints)
        return MissionPlan(wps, home, self.source)


@dataclass(frozen=True)
class MissionItemInt:
    """A MAVLink mission item as ``MISSION_ITEM_INT`` carries it, field for field: x/y are
    degE7 in a global frame, metres times ``LOCAL_SCALE`` in ``MAV_FRAME_LOCAL_NED``. The one
    type for an item, uploaded from a plan, downloaded from an autopilot, or stored by one."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = 0

    @property
    def lat_deg(self) -> float:
        return self.x / DEG_E7

    @property
    def lon_deg(self) -> float:
        return self.y / DEG_E7

    @property
    def command_name(self) -> str:
        """``MAV_CMD_NAV_WAYPOINT`` etc. (the number for a command MAVLink does not name)."""
        entry = mavlink.enums["MAV_CMD"].get(self.command)
        return entry.name if entry is not None else str(self.command)

    @property
    def is_navigation(self) -> bool:
        """True for items that move the vehicle to a position (waypoint, takeoff, land...)."""
        return self.command in (CMD_WAYPOINT, CMD_TAKEOFF, CMD_LAND, CMD_LOITER_TIME,
                                mavlink.MAV_CMD_NAV_LOITER_UNLIM)

    @classmethod
    def from_message(cls, msg: Any) -> MissionItemInt:
        """From ``MISSION_ITEM_INT``, or the deprecated float ``MISSION_ITEM`` (its x/y scaled
        to the INT encoding)."""
        frame = int(msg.frame)
        x, y = msg.x, msg.y
        if msg.get_type() == "MISSION_ITEM":
            scale = DEG_E7 if frame in GLOBAL_FRAMES else LOCAL_SCALE
            x, y = round(float(x) * scale), round(float(y) * scale)
        return cls(
            seq=int(msg.seq), frame=frame, command=int(msg.command), current=int(msg.current),
            autocontinue=int(msg.autocontinue), param1=float(msg.param1), param2=float(msg.param2),
            param3=float(msg.param3), param4=float(msg.param4), x=int(x), y=int(y), z=float(msg.z),
            mission_type=int(getattr(msg, "mission_type", mavlink.MAV_MISSION_TYPE_MISSION)),
        )


def command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(command)
    return f"{command} ({entry.name})" if entry is not None else str(command)


# --- MAVLink items <-> plan -------------------------------------------------------------------

@dataclass
class ItemMap:
    """MAVLink items built from a plan and, per item, the waypoint index it came from."""

    items: list[MissionItemInt] = field(default_factory=list)
    waypoint_index: list[int] = field(default_factory=list)


def plan_to_items(plan: MissionPlan) -> ItemMap:
    """MAVLink mission items (frame GLOBAL_RELATIVE_ALT_INT) for a resolved (global) plan.

    A DO_CHANGE_SPEED item precedes each waypoint whose speed differs from the one before.
    A take-off or land step without a position gets one, as QGroundControl gives it: take-off
    the plan's home, land the position of the step before it (home when there is none). An
    INT item cannot say "here" (PX4 flies latitude/longitude 0/0 literally), so a step that
    cannot be given a position is an error, never encoded as 0/0.
    """
    out = ItemMap()
    speed: float | None = None
    home_ll = (plan.home.lat_deg, plan.home.lon_deg) if plan.home is not None else None
    last_ll = home_ll

    def position_of(i: int, w: Waypoint, fallback: tuple[float, float] | None) -> tuple[float, float]:
        if math.isfinite(w.lat_deg) and math.isfinite(w.lon_deg):
            return w.lat_deg, w.lon_deg
        if fallback is None:
            raise MissionError(f"{plan.source}: waypoint {i} ({w.action}) has no position and the plan "
                               "has no home to take one from: give 'home' in the file, a position "
                               "for the step, or upload to a vehicle that reports its home")
        return fallback

    def add(idx: int, frame: int, cmd: int, p1: float, p2: float, p3: float, p4: float,
            lat: float, lon: float, alt: float) -> None:
        seq = len(out.items)
        x = int(round(lat * 1e7)) if math.isfinite(lat) else 0
        y = int(round(lon * 1e7)) if math.isfinite(lon) else 0
        out.items.append(MissionItemInt(seq, frame, cmd, int(seq == 0), 1, p1, p2, p3, p4,
                                        x, y, alt))
        out.waypoint_index.append(idx)

    for i, w in enumerate(plan.waypoints):
        if w.is_local:
            raise MissionError(f"{plan.source}: waypoint {i} is local; resolve the plan first")
        if w.speed_m_s is not None and w.speed_m_s != speed:
            speed = w.speed_m_s
            add(i, FRAME_MISSION, CMD_CHANGE_SPEED, 1.0, speed, -1.0, 0.0, _NAN, _NAN, _NAN)
        yaw = w.yaw_deg if w.yaw_deg is not None else _NAN
        if w.action == "rtl":
            add(i, FRAME_MISSION, CMD_RTL, 0, 0, 0, 0, _NAN, _NAN, 0.0)
        elif w.action == "takeoff":
            lat, lon = position_of(i, w, home_ll if home_ll is not None else last_ll)
            add(i, FRAME_GLOBAL_REL_INT, CMD_TAKEOFF, 0, 0, 0, yaw, lat, lon, w.rel_alt_m)
            last_ll = (lat, lon)
        elif w.action == "land":
            lat, lon = position_of(i, w, last_ll)
            add(i, FRAME_GLOBAL_REL_INT, CMD_LAND, 0, 0, 0, yaw, lat, lon, 0.0)
            last_ll = (lat, lon)
        else:
            lat, lon = position_of(i, w, None)
            accept = w.acceptance_radius_m if w.acceptance_radius_m is not None else 0.0
            add(i, FRAME_GLOBAL_REL_INT, CMD_WAYPOINT, w.hold_s, accept, 0.0, yaw, lat, lon,
                w.rel_alt_m)
            last_ll = (lat, lon)
    return out


def _nan_to_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def items_to_plan(items: list[MissionItemInt], home: GeoOrigin | None,
                  source: str, label: str = "item {i}") -> MissionPlan:
    """Inverse of :func:`plan_to_items` (for downloads and ``.plan`` files).

    Raises :class:`MissionError` naming the item (``label`` formatted with its index ``i``)
    for commands or frames a plan cannot hold.
    """
    wps: list[Waypoint] = []
    speed: float | None = None
    for i, it in enumerate(items):
        where = f"{source}: {label.format(i=i)}"
        if it.command == CMD_CHANGE_SPEED:
            if it.param2 > 0:
                speed = it.param2
            continue
        if it.command not in (CMD_WAYPOINT, CMD_LOITER_TIME, CMD_TAKEOFF, CMD_LAND, CMD_RTL):
            raise MissionError(f"{where}: unsupported command {command_name(it.command)}")
        if it.command == CMD_RTL:
            wps.append(Waypoint(action="rtl", speed_m_s=speed))
            continue
        if it.frame in (FRAME_GLOBAL_REL, FRAME_GLOBAL_REL_INT):
            rel = it.z
        elif it.frame in (FRAME_GLOBAL, FRAME_GLOBAL_INT):
            if home is None:
                raise MissionError(f"{where}: AMSL altitude (frame {it.frame}) needs a home")
            rel = it.z - home.alt_m
        else:
            raise MissionError(f"{where}: unsupported frame {it.frame} for command "
                               f"{command_name(it.command)} (use 0 or 3)")
        has_pos = it.x != 0 or it.y != 0
        lat = it.lat_deg if has_pos else _NAN
        lon = it.lon_deg if has_pos else _NAN
        yaw = _nan_to_none(it.param4)
        if it.command == CMD_TAKEOFF:
            wps.append(Waypoint("takeoff", lat, lon, rel, speed_m_s=speed, yaw_deg=yaw))
        elif it.command == CMD_LAND:
            wps.append(Waypoint("land", lat, lon, 0.0, speed_m_s=speed, yaw_deg=yaw))
        else:
            if not has_pos:
                raise MissionError(f"{where}: waypoint without latitude/longitude")
            accept = it.param2 if it.command == CMD_WAYPOINT and it.param2 > 0 else None
            wps.append(Waypoint("waypoint", lat, lon, rel, speed_m_s=speed,
                                hold_s=max(0.0, it.param1), acceptance_radius_m=accept,
                                yaw_deg=yaw))
    return MissionPlan(tuple(wps), home, source)
