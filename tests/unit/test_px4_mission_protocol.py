"""The mock autopilot's mission protocol state machine, driven without sockets.

A simulated client uploads over a lossy channel (requests and items dropped or duplicated at
random); whatever the loss pattern, the vehicle ends with exactly the uploaded items or,
when it gives up, with its previous mission and a MISSION_ACK saying so.
"""

from __future__ import annotations

import random
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.sim.autopilot.mission_server import MissionServer

CLIENT = (245, 190)


class _Wire:
    """Loopback between a MissionServer and a scripted client, with loss and duplication."""

    def __init__(self, seed: int, loss: float, dup: float) -> None:
        self.rng = random.Random(seed)
        self.loss, self.dup = loss, dup
        self.vehicle_mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.client_mav = mavlink.MAVLink(None, srcSystem=CLIENT[0], srcComponent=CLIENT[1])
        self.to_client: list[Any] = []
        self.server = MissionServer(self.vehicle_mav, self._from_vehicle)
        self.server.max_attempts = 50

    def _roundtrip(self, msg: Any, mav: mavlink.MAVLink) -> Any:
        parser = mavlink.MAVLink(None)
        return parser.parse_buffer(msg.pack(mav))[0]

    def _from_vehicle(self, msg: Any) -> None:
        if self.rng.random() < self.loss:
            return
        out = self._roundtrip(msg, self.vehicle_mav)
        self.to_client.extend([out] * (2 if self.rng.random() < self.dup else 1))

    def to_vehicle(self, msg: Any, now_s: float) -> None:
        if self.rng.random() < self.loss:
            return
        m = self._roundtrip(msg, self.client_mav)
        for _ in range(2 if self.rng.random() < self.dup else 1):
            self.server.handle(m, now_s)


def _item(mav: mavlink.MAVLink, seq: int) -> Any:
    return mav.mission_item_int_encode(
        1, 1, seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT,
        int(seq == 0), 1, 0.0, 0.5, 0.0, 0.0, 473977420 + seq * 100, 85455940, 2.0 + seq)


def _upload(wire: _Wire, n: int) -> int | None:
    """Run a client upload of ``n`` items; returns the final MISSION_ACK type (None = none)."""
    mav = wire.client_mav
    now = 0.0
    wire.to_vehicle(mav.mission_count_encode(1, 1, n, 0), now)
    client_retries = 0
    for _ in range(5000):
        now += 0.05
        wire.server.tick(now)
        msgs, wire.to_client = wire.to_client, []
        for msg in msgs:
            if msg.get_type() == "MISSION_REQUEST_INT":
                wire.to_vehicle(_item(mav, msg.seq), now)
            elif msg.get_type() == "MISSION_ACK":
                return int(msg.type)
        if not wire.server.upload_in_progress and not msgs:
            # The count itself was lost (or our last item's ACK): the client retries, as
            # MAVSDK does, by re-sending the count (or the last item).
            client_retries += 1
            if client_retries > 200:
                return None
            if len(wire.server.items()) == n:
                wire.to_vehicle(_item(mav, n - 1), now)
            else:
                wire.to_vehicle(mav.mission_count_encode(1, 1, n, 0), now)
    return None


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 25), st.integers(0, 10_000), st.sampled_from([0.0, 0.1, 0.3]),
       st.sampled_from([0.0, 0.2]))
def test_upload_over_a_lossy_channel_stores_exactly_the_items(n: int, seed: int, loss: float,
                                                              dup: float) -> None:
    wire = _Wire(seed, loss, dup)
    result = _upload(wire, n)
    stored = wire.server.items()
    if result == mavlink.MAV_MISSION_ACCEPTED or (result is None and len(stored) == n):
        assert [it.seq for it in stored] == list(range(n))
        assert [it.z for it in stored] == [2.0 + i for i in range(n)]
        assert stored[3 % n].x == 473977420 + (3 % n) * 100
    else:
        # gave up: the previous (empty) mission is kept, never a partial one
        assert stored == []


def test_download_returns_what_was_uploaded_and_rejects_bad_seq() -> None:
    wire = _Wire(0, 0.0, 0.0)
    assert _upload(wire, 4) == mavlink.MAV_MISSION_ACCEPTED
    mav = wire.client_mav
    wire.to_vehicle(mav.mission_request_list_encode(1, 1, 0), 0.0)
    assert wire.to_client.pop().count == 4
    wire.to_vehicle(mav.mission_request_int_encode(1, 1, 2, 0), 0.0)
    item = wire.to_client.pop()
    assert (item.get_type(), item.seq, item.z) == ("MISSION_ITEM_INT", 2, 4.0)
    wire.to_vehicle(mav.mission_request_int_encode(1, 1, 9, 0), 0.0)
    assert wire.to_client.pop().type == mavlink.MAV_MISSION_INVALID_SEQUENCE


def test_second_uploader_is_refused_while_one_is_in_progress() -> None:
    wire = _Wire(0, 0.0, 0.0)
    wire.to_vehicle(wire.client_mav.mission_count_encode(1, 1, 3, 0), 0.0)
    other = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    msg = mavlink.MAVLink(None).parse_buffer(other.mission_count_encode(1, 1, 2, 0).pack(other))[0]
    wire.server.handle(msg, 0.0)
    acks = [m for m in wire.to_client if m.get_type() == "MISSION_ACK"]
    assert acks and acks[-1].type == mavlink.MAV_MISSION_DENIED
    assert wire.server.upload_in_progress


def test_unsupported_command_is_rejected_with_its_result() -> None:
    wire = _Wire(0, 0.0, 0.0)
    mav = wire.client_mav
    wire.to_vehicle(mav.mission_count_encode(1, 1, 1, 0), 0.0)
    wire.to_vehicle(mav.mission_item_int_encode(1, 1, 0, 2, 31000, 1, 1, 0, 0, 0, 0, 0, 0, 0),
                    0.0)
    ack = [m for m in wire.to_client if m.get_type() == "MISSION_ACK"][-1]
    assert ack.type == mavlink.MAV_MISSION_UNSUPPORTED and wire.server.items() == []
