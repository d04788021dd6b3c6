"""Mission download through our own link (the MAVLink mission protocol, client side).

The sequence (MAVLink mission microservice, "download a mission from a drone")::

    we -> MISSION_REQUEST_LIST            autopilot -> MISSION_COUNT(count)
    we -> MISSION_REQUEST_INT(seq)        autopilot -> MISSION_ITEM_INT(seq)   for each seq
    we -> MISSION_ACK(MAV_MISSION_ACCEPTED)

Every request is resent after ``timeout_s`` up to ``retries`` times; an item with another
sequence number than asked for is ignored (a late answer to an earlier request). A
``MISSION_ACK`` with an error from the autopilot, or exhausted retries, raise
:class:`~companion.errors.MissionError` naming the step or item.

:func:`waypoint_ned_m` turns an item into a local NED position relative to home so the
service can fly the mission leg by leg with offboard setpoints.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.mavlink.link import MavlinkLink, Message, Subscription
from companion.mavlink.state import HomePosition, Vec3
from companion.missions import FRAME_LOCAL_NED, LOCAL_SCALE, MissionItemInt

log = logging.getLogger(__name__)

#: WGS84 equatorial radius; flat-earth offsets are fine over a mission's few hundred metres.
_EARTH_RADIUS_M = 6378137.0

_GLOBAL_FRAMES = {
    mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT,
}
_RELATIVE_FRAMES = {
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
}


def waypoint_ned_m(item: MissionItemInt, home: HomePosition) -> Vec3:
    """The item's position in PX4 local NED (metres), via the home position.

    Raises :class:`MissionError` for frames we cannot place (e.g. terrain-relative).
    """
    if item.frame == FRAME_LOCAL_NED:
        return item.x / LOCAL_SCALE, item.y / LOCAL_SCALE, item.z
    if item.frame in _GLOBAL_FRAMES:
        up_m = item.z - home.altitude_amsl_m
    elif item.frame in _RELATIVE_FRAMES:
        up_m = item.z
    else:
        raise MissionError(
            f"mission item {item.seq} ({item.command_name}): frame {item.frame} is not supported "
            "(use a global, relative-altitude or local NED frame)"
        )
    lat0 = math.radians(home.latitude_deg)
    north_m = math.radians(item.lat_deg - home.latitude_deg) * _EARTH_RADIUS_M
    east_m = math.radians(item.lon_deg - home.longitude_deg) * _EARTH_RADIUS_M * math.cos(lat0)
    hn, he, hd = home.position_ned_m
    return hn + north_m, he + east_m, hd - up_m


_MISSION_TYPES = ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_ACK")


class _Download:
    def __init__(self, link: MavlinkLink, sub: Subscription, target_system: int,
                 target_component: int, mission_type: int, timeout_s: float, retries: int) -> None:
        self.link = link
        self.sub = sub
        self.ts = target_system
        self.tc = target_component
        self.mission_type = mission_type
        self.timeout_s = timeout_s
        self.retries = retries

    def _ours(self, msg: Message) -> bool:
        if msg.get_srcSystem() != self.ts or (self.tc and msg.get_srcComponent() != self.tc):
            return False
        if getattr(msg, "mission_type", self.mission_type) != self.mission_type:
            return False
        return getattr(msg, "target_system", 0) in (0, self.link.system_id)

    async def _next(self, want: str, seq: int | None, deadline_s: float) -> Message | None:
        loop = asyncio.get_running_loop()
        while True:
            remaining = deadline_s - loop.time()
            if remaining <= 0:
                return None
            try:
                msg = await self.sub.get(remaining)
            except TimeoutError:
                return None
            if not self._ours(msg):
                continue
            mtype = msg.get_type()
            if mtype == "MISSION_ACK":
                if msg.type != mavlink.MAV_MISSION_ACCEPTED:
                    name = mavlink.enums["MAV_MISSION_RESULT"][msg.type].name \
                        if msg.type in mavlink.enums["MAV_MISSION_RESULT"] else str(msg.type)
                    where = f"item {seq}" if seq is not None else "the item count"
                    raise MissionError(f"mission download: autopilot aborted while we asked for "
                                       f"{where}: {name}")
                continue
            if want == "MISSION_COUNT" and mtype == "MISSION_COUNT":
                return msg
            if want == "ITEM" and mtype in ("MISSION_ITEM_INT", "MISSION_ITEM") and msg.seq == seq:
                return msg

    async def _request(
        self, build: Callable[[], Message], want: str, seq: int | None, what: str
    ) -> Message:
        loop = asyncio.get_running_loop()
        for attempt in range(self.retries + 1):
            self.link.send(build())
            msg = await self._next(want, seq, loop.time() + self.timeout_s)
            if msg is not None:
                return msg
            log.info("mission download: no answer for %s (attempt %d/%d)", what, attempt + 1,
                     self.retries + 1)
        raise MissionError(f"mission download: no answer for {what} from "
                           f"{self.ts}/{self.tc} after {self.retries + 1} attempts")

    async def run(self) -> tuple[MissionItemInt, ...]:
        mav = self.link.mav
        count_msg = await self._request(
            lambda: mav.mission_request_list_encode(self.ts, self.tc, self.mission_type),
            "MISSION_COUNT", None, "the item count (MISSION_REQUEST_LIST)",
        )
        count = int(count_msg.count)
        items: list[MissionItemInt] = []
        for seq in range(count):
            msg = await self._request(
                functools.partial(mav.mission_request_int_encode, self.ts, self.tc, seq,
                                  self.mission_type),
                "ITEM", seq, f"mission item {seq} of {count}",
            )
            items.append(MissionItemInt.from_message(msg))
        self.link.send(mav.mission_ack_encode(
            self.ts, self.tc, mavlink.MAV_MISSION_ACCEPTED, self.mission_type
        ))
        log.info("downloaded a mission of %d items", count)
        return tuple(items)


async def download_mission(
    link: MavlinkLink,
    target_system: int = 1,
    target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
    *,
    mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION,
    timeout_s: float = 1.5,
    retries: int = 3,
) -> tuple[MissionItemInt, ...]:
    """Download the autopilot's mission (items in sequence order). Raises :class:`MissionError`."""
    async with link.subscribe(*_MISSION_TYPES, maxsize=256) as sub:
        return await _Download(link, sub, target_system, target_component, mission_type,
                               timeout_s, retries).run()
