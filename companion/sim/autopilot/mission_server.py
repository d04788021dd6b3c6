"""The autopilot side of the MAVLink mission protocol (upload, download, clear, set current).

Implements https://mavlink.io/en/services/mission.html as PX4 does for the three mission types
(mission, geofence, rally): the vehicle drives uploads by requesting items with
``MISSION_REQUEST_INT`` and re-requests an item when it does not arrive within
:attr:`MissionServer.item_timeout_s`; duplicates (a client re-sending an item it thinks was lost)
are ignored; a finished upload is acknowledged again if the client repeats its last item.
Items are stored exactly as received so a download returns what was uploaded.

The server does not fly anything; the navigator reads :meth:`MissionServer.items` and is told
about changes through ``on_mission_changed``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.missions import MissionItemInt as MissionItem

log = logging.getLogger(__name__)

MISSION_TYPES = (
    mavlink.MAV_MISSION_TYPE_MISSION,
    mavlink.MAV_MISSION_TYPE_FENCE,
    mavlink.MAV_MISSION_TYPE_RALLY,
)

#: Frames whose x/y are latitude/longitude (degE7 in the *_INT messages).
GLOBAL_FRAMES = frozenset({
    mavlink.MAV_FRAME_GLOBAL,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
    mavlink.MAV_FRAME_GLOBAL_INT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
})
SUPPORTED_FRAMES = GLOBAL_FRAMES | {mavlink.MAV_FRAME_MISSION}

#: Mission commands the navigator understands (others are rejected as MAV_MISSION_UNSUPPORTED).
SUPPORTED_COMMANDS = frozenset({
    mavlink.MAV_CMD_NAV_WAYPOINT,
    mavlink.MAV_CMD_NAV_LOITER_UNLIM,
    mavlink.MAV_CMD_NAV_LOITER_TIME,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_NAV_TAKEOFF,
    mavlink.MAV_CMD_NAV_DELAY,
    mavlink.MAV_CMD_DO_CHANGE_SPEED,
    mavlink.MAV_CMD_DO_JUMP,
    mavlink.MAV_CMD_DO_SET_HOME,
    mavlink.MAV_CMD_CONDITION_YAW,
    mavlink.MAV_CMD_DO_MOUNT_CONTROL,
    mavlink.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
    mavlink.MAV_CMD_DO_SET_CAM_TRIGG_DIST,
    mavlink.MAV_CMD_IMAGE_START_CAPTURE,
    mavlink.MAV_CMD_IMAGE_STOP_CAPTURE,
    mavlink.MAV_CMD_VIDEO_START_CAPTURE,
    mavlink.MAV_CMD_VIDEO_STOP_CAPTURE,
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    mavlink.MAV_CMD_NAV_RALLY_POINT,
})


def item_from_msg(msg: Any) -> MissionItem:
    """A stored item from a ``MISSION_ITEM_INT`` or the legacy float ``MISSION_ITEM``."""
    x, y = msg.x, msg.y
    if msg.get_type() == "MISSION_ITEM":
        scale = 1e7 if msg.frame in GLOBAL_FRAMES else 1e4
        x, y = int(round(x * scale)), int(round(y * scale))
    return MissionItem(
        seq=int(msg.seq), frame=int(msg.frame), command=int(msg.command),
        current=int(msg.current), autocontinue=int(msg.autocontinue),
        param1=float(msg.param1), param2=float(msg.param2), param3=float(msg.param3),
        param4=float(msg.param4), x=int(x), y=int(y), z=float(msg.z),
        mission_type=int(getattr(msg, "mission_type", 0)),
    )


def validate_item(item: MissionItem) -> int:
    """``MAV_MISSION_RESULT`` for one uploaded item (``MAV_MISSION_ACCEPTED`` if fine)."""
    if item.command not in SUPPORTED_COMMANDS:
        return int(mavlink.MAV_MISSION_UNSUPPORTED)
    if item.frame not in SUPPORTED_FRAMES:
        return int(mavlink.MAV_MISSION_UNSUPPORTED_FRAME)
    if item.frame in GLOBAL_FRAMES:
        if not -900_000_000 <= item.x <= 900_000_000:
            return int(mavlink.MAV_MISSION_INVALID_PARAM5_X)
        if not -1_800_000_000 <= item.y <= 1_800_000_000:
            return int(mavlink.MAV_MISSION_INVALID_PARAM6_Y)
        if not math.isfinite(item.z):
            return int(mavlink.MAV_MISSION_INVALID_PARAM7)
    return int(mavlink.MAV_MISSION_ACCEPTED)


@dataclass
class _Upload:
    partner: tuple[int, int]  # (system id, component id) of the uploader
    mission_type: int
    count: int
    items: list[MissionItem] = field(default_factory=list)
    attempts: int = 0
    last_activity_s: float = 0.0


class MissionServer:
    """Mission storage and protocol state for one vehicle.

    ``send(msg)`` transmits a pymavlink message; ``mav`` encodes them. ``reject_seq`` (a fault
    hook) names an item index whose upload fails with ``MAV_MISSION_DENIED``.
    """

    def __init__(
        self,
        mav: mavlink.MAVLink,
        send: Callable[[Any], None],
        on_mission_changed: Callable[[int], None] | None = None,
        on_set_current: Callable[[int], bool] | None = None,
    ) -> None:
        self._mav = mav
        self._send = send
        self._on_changed = on_mission_changed
        self._set_current_cb = on_set_current
        self._plans: dict[int, list[MissionItem]] = {t: [] for t in MISSION_TYPES}
        self._upload: _Upload | None = None
        self._last_completed: tuple[tuple[int, int], int, int] | None = None
        self.item_timeout_s = 0.4
        self.max_attempts = 6
        #: Fault hook: returns the item index whose upload is to be rejected, or None.
        self.reject_seq: Callable[[], int | None] | None = None
        self.uploads_completed = 0

    def items(self, mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION) -> list[MissionItem]:
        """A copy of the stored items of ``mission_type``."""
        return list(self._plans.get(mission_type, []))

    @property
    def upload_in_progress(self) -> bool:
        return self._upload is not None

    # --- message handling ----------------------------------------------------------------

    def handle(self, msg: Any, now_s: float) -> bool:
        """Process a mission-protocol message; returns False if it is not one."""
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return False
        handler(self, msg, now_s)
        return True

    def _partner(self, msg: Any) -> tuple[int, int]:
        return int(msg.get_srcSystem()), int(msg.get_srcComponent())

    def _ack(self, partner: tuple[int, int], result: int, mission_type: int) -> None:
        self._send(self._mav.mission_ack_encode(partner[0], partner[1], result, mission_type))

    def _request(self, up: _Upload, seq: int) -> None:
        self._send(self._mav.mission_request_int_encode(up.partner[0], up.partner[1], seq,
                                                        up.mission_type))

    def _on_count(self, msg: Any, now_s: float) -> None:
        partner = self._partner(msg)
        mtype = int(getattr(msg, "mission_type", 0))
        if mtype not in self._plans:
            self._ack(partner, mavlink.MAV_MISSION_UNSUPPORTED, mtype)
            return
        if self._upload is not None and self._upload.partner != partner:
            log.warning("mission upload from %s refused: upload from %s in progress",
                        partner, self._upload.partner)
            self._ack(partner, mavlink.MAV_MISSION_DENIED, mtype)
            return
        count = int(msg.count)
        if count == 0:
            self._upload = None
            self._commit(mtype, [])
            self._ack(partner, mavlink.MAV_MISSION_ACCEPTED, mtype)
            return
        log.info("mission upload (type %d) of %d items from %s", mtype, count, partner)
        self._upload = _Upload(partner, mtype, count, last_activity_s=now_s)
        self._last_completed = None
        self._request(self._upload, 0)

    def _on_item(self, msg: Any, now_s: float) -> None:
        partner = self._partner(msg)
        item = item_from_msg(msg)
        up = self._upload
        if up is None or up.partner != partner or up.mission_type != item.mission_type:
            done = self._last_completed
            if done is not None and done[0] == partner and item.seq == done[2] - 1:
                # The client missed our final ACK and re-sent its last item.
                self._ack(partner, mavlink.MAV_MISSION_ACCEPTED, done[1])
            return
        expected = len(up.items)
        if item.seq < expected:
            return  # duplicate of an item we already have
        if item.seq > expected:
            self._request(up, expected)
            return
        result = validate_item(item)
        reject = self.reject_seq() if self.reject_seq is not None else None
        if reject is not None and item.seq == reject:
            result = int(mavlink.MAV_MISSION_DENIED)
        if result != mavlink.MAV_MISSION_ACCEPTED:
            log.warning("mission item %d (command %d, frame %d) rejected: %s", item.seq,
                        item.command, item.frame, mavlink.enums["MAV_MISSION_RESULT"][result].name)
            self._upload = None
            self._ack(partner, result, up.mission_type)
            return
        up.items.append(item)
        up.attempts = 0
        up.last_activity_s = now_s
        if len(up.items) == up.count:
            self._upload = None
            self._last_completed = (partner, up.mission_type, up.count)
            self._commit(up.mission_type, up.items)
            self.uploads_completed += 1
            self._ack(partner, mavlink.MAV_MISSION_ACCEPTED, up.mission_type)
        else:
            self._request(up, len(up.items))

    def _on_request_list(self, msg: Any, now_s: float) -> None:
        mtype = int(getattr(msg, "mission_type", 0))
        partner = self._partner(msg)
        if mtype not in self._plans:
            self._ack(partner, mavlink.MAV_MISSION_UNSUPPORTED, mtype)
            return
        self._send(self._mav.mission_count_encode(partner[0], partner[1],
                                                  len(self._plans[mtype]), mtype))

    def _on_request(self, msg: Any, now_s: float) -> None:
        mtype = int(getattr(msg, "mission_type", 0))
        partner = self._partner(msg)
        plan = self._plans.get(mtype)
        if plan is None:
            self._ack(partner, mavlink.MAV_MISSION_UNSUPPORTED, mtype)
            return
        seq = int(msg.seq)
        if not 0 <= seq < len(plan):
            self._ack(partner, mavlink.MAV_MISSION_INVALID_SEQUENCE, mtype)
            return
        it = plan[seq]
        if msg.get_type() == "MISSION_REQUEST":
            scale = 1e-7 if it.frame in GLOBAL_FRAMES else 1e-4
            out = self._mav.mission_item_encode(
                partner[0], partner[1], it.seq, it.frame, it.command, it.current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                it.x * scale, it.y * scale, it.z, mtype)
        else:
            out = self._mav.mission_item_int_encode(
                partner[0], partner[1], it.seq, it.frame, it.command, it.current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z,
                mtype)
        self._send(out)

    def _on_clear_all(self, msg: Any, now_s: float) -> None:
        mtype = int(getattr(msg, "mission_type", 0))
        partner = self._partner(msg)
        types = MISSION_TYPES if mtype == mavlink.MAV_MISSION_TYPE_ALL else (mtype,)
        if any(t not in self._plans for t in types):
            self._ack(partner, mavlink.MAV_MISSION_UNSUPPORTED, mtype)
            return
        for t in types:
            self._commit(t, [])
        self._ack(partner, mavlink.MAV_MISSION_ACCEPTED, mtype)

    def _on_set_current(self, msg: Any, now_s: float) -> None:
        if self._set_current_cb is not None:
            self._set_current_cb(int(msg.seq))

    def _on_ack(self, msg: Any, now_s: float) -> None:
        # The end of a download, or a client cancelling our upload.
        up = self._upload
        if up is not None and up.partner == self._partner(msg):
            log.info("mission upload cancelled by client (result %d)", msg.type)
            self._upload = None

    _handlers: dict[str, Callable[[MissionServer, Any, float], None]] = {
        "MISSION_COUNT": _on_count,
        "MISSION_ITEM_INT": _on_item,
        "MISSION_ITEM": _on_item,
        "MISSION_REQUEST_LIST": _on_request_list,
        "MISSION_REQUEST_INT": _on_request,
        "MISSION_REQUEST": _on_request,
        "MISSION_CLEAR_ALL": _on_clear_all,
        "MISSION_SET_CURRENT": _on_set_current,
        "MISSION_ACK": _on_ack,
    }

    # --- time-driven retries -------------------------------------------------------------

    def tick(self, now_s: float) -> None:
        """Re-request a missing item after a timeout; give up after ``max_attempts``."""
        up = self._upload
        if up is None or now_s - up.last_activity_s < self.item_timeout_s:
            return
        up.attempts += 1
        up.last_activity_s = now_s
        if up.attempts > self.max_attempts:
            log.warning("mission upload timed out waiting for item %d of %d",
                        len(up.items), up.count)
            self._upload = None
            self._ack(up.partner, mavlink.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)
            return
        self._request(up, len(up.items))

    def _commit(self, mission_type: int, items: list[MissionItem]) -> None:
        self._plans[mission_type] = list(items)
        if self._on_changed is not None:
            self._on_changed(mission_type)
