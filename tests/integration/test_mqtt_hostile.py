"""Hostile ground-link input against a real Mosquitto broker (issue 33, item 5).

Every malformed command gets an error reply and never reaches the service; a retained
command is refused even when the broker delivers it live; the per-vehicle ACL of
docs/mqtt.md keeps one ground credential from commanding another vehicle.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from mosquitto_broker import MosquittoBroker

from companion.config import MqttConfig
from companion.ground import CommandValidator, MqttBridge

pytestmark = pytest.mark.asyncio

REPO = Path(__file__).resolve().parents[2]
WAIT_S = 15.0  # generous: the machine is shared; nothing here measures time


def mqtt_cfg(broker: MosquittoBroker, vehicle: str = "drone1", **kw: Any) -> MqttConfig:
    return MqttConfig(host=broker.host, port=broker.port, vehicle_id=vehicle,
                      topic_prefix="companion", reconnect_min_s=0.1, reconnect_max_s=0.5,
                      keepalive_s=5, timeout_s=5.0, **kw)


def validator() -> CommandValidator:
    return CommandValidator(geofence_xy_m=(0.0, 0.0, 8.0, 6.0), max_altitude_m=3.0,
                            rate_limit_hz=50.0, burst=50)


class Ground:
    """A ground station recording every message it may read."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.received: list[tuple[str, bytes]] = []
        self._new = asyncio.Event()

    async def pump(self) -> None:
        async for m in self.client.messages:
            payload = m.payload if isinstance(m.payload, bytes) else str(m.payload).encode()
            self.received.append((m.topic.value, payload))
            self._new.set()

    async def wait_for(self, topic: str,
                       pred: Callable[[dict[str, Any]], bool] = lambda m: True) -> dict[str, Any]:
        async def _wait() -> dict[str, Any]:
            while True:
                for t, p in self.received:
                    if t == topic and pred(msg := json.loads(p)):
                        return msg
                self._new.clear()
                await self._new.wait()
        try:
            return await asyncio.wait_for(_wait(), WAIT_S)
        except asyncio.TimeoutError:
            pytest.fail(f"nothing matching on {topic}; got {sorted({t for t, _ in self.received})}")

    def topics(self) -> set[str]:
        return {t for t, _ in self.received}


@contextlib.asynccontextmanager
async def ground_station(broker: MosquittoBroker, subscribe: str, name: str, *,
                         username: str | None = None,
                         password: str | None = None) -> AsyncIterator[Ground]:
    async with aiomqtt.Client(broker.host, broker.port, username=username, password=password,
                              identifier=name) as client:
        await client.subscribe(subscribe, qos=1)
        ground = Ground(client)
        task = asyncio.create_task(ground.pump())
        try:
            yield ground
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await task


async def next_command(bridge: MqttBridge) -> Any:
    async def first() -> Any:
        async for cmd in bridge.commands():
            return cmd
    return await asyncio.wait_for(first(), WAIT_S)


@pytest.fixture
def broker(tmp_path: Path) -> Any:
    b = MosquittoBroker(tmp_path / "broker").start()
    yield b
    b.stop()


HOLD = {"schema_version": 1, "request_id": "ok-1", "action": "hold"}
REPLY = "companion/drone1/reply"


@pytest.mark.parametrize(("name", "payload", "reason"), [
    ("4000_nested_brackets", b"[" * 4000, "goal: JSON nested more than 8 levels deep"),
    ("4000_nested_objects", b'{"a":' * 800, "goal: JSON nested more than 8 levels deep"),
    ("duplicate_json_keys",
     b'{"schema_version": 1, "request_id": "d-1", "x_m": 1.0, "y_m": 1.0, "x_m": 7.0}',
     "goal: duplicate key 'x_m'"),
    ("invalid_utf8", b'{"schema_version": 1, "request_id": "\xff\xfe", "x_m": 1, "y_m": 1}',
     "goal: not valid UTF-8 (byte 0xff at offset 37)"),
])
async def test_malformed_command_gets_an_error_reply(broker: MosquittoBroker, name: str,
                                                     payload: bytes, reason: str) -> None:
    async with ground_station(broker, "companion/drone1/#", f"ground-{name}") as ground, \
            MqttBridge(mqtt_cfg(broker), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        await ground.client.publish("companion/drone1/cmd/goal", payload, qos=1)
        await ground.client.publish("companion/drone1/cmd/vehicle", json.dumps(HOLD), qos=1)
        reply = await ground.wait_for(REPLY, lambda m: m["command"] == "goal")
        assert reply["ok"] is False and reply["reason"] == reason
        assert "utf-16" not in reply["reason"]
        # The bridge kept working and only the valid command reached the service.
        assert (await next_command(bridge)).request_id == "ok-1"
        assert bridge.stats.commands_rejected == 1 and bridge.stats.commands_accepted == 1


async def test_retained_command_delivered_live_is_refused(broker: MosquittoBroker) -> None:
    async with ground_station(broker, "companion/drone1/#", "ground-retain") as ground, \
            MqttBridge(mqtt_cfg(broker), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        # The bridge is subscribed already: the broker forwards this one live, not from store.
        land = {"schema_version": 1, "request_id": "r-live", "action": "land"}
        await ground.client.publish("companion/drone1/cmd/vehicle", json.dumps(land), qos=1,
                                    retain=True)
        await ground.client.publish("companion/drone1/cmd/vehicle", json.dumps(HOLD), qos=1)
        reply = await ground.wait_for(REPLY, lambda m: m["request_id"] == "r-live")
        assert reply["ok"] is False and "retained commands are refused" in reply["reason"]
        assert (await next_command(bridge)).request_id == "ok-1"
        await ground.client.publish("companion/drone1/cmd/vehicle", b"", qos=1, retain=True)


def docs_acl() -> str:
    text = (REPO / "docs" / "mqtt.md").read_text(encoding="utf-8")
    match = re.search(r"<!-- acl: per-vehicle -->\s*```\n(.*?)```", text, re.S)
    assert match, "docs/mqtt.md lost its per-vehicle ACL example"
    return match.group(1)


USERS = {"drone1": "p-d1", "drone2": "p-d2", "ground-drone1": "p-g1",
         "ground-drone2": "p-g2", "ground-fleet": "p-gf"}


@pytest.fixture
def acl_broker(tmp_path: Path) -> Any:
    b = MosquittoBroker(tmp_path / "acl", passwords=USERS, acl=docs_acl()).start()
    yield b
    b.stop()


@contextlib.asynccontextmanager
async def vehicle(broker: MosquittoBroker, tmp_path: Path, name: str) -> AsyncIterator[MqttBridge]:
    pw = tmp_path / f"{name}.password"
    pw.write_text(USERS[name] + "\n")
    async with MqttBridge(mqtt_cfg(broker, name, username=name, password_file=str(pw)),
                          validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        yield bridge


def _cmd(rid: str) -> str:
    return json.dumps({"schema_version": 1, "request_id": rid, "action": "hold"})


async def test_one_ground_credential_does_not_command_the_fleet(acl_broker: MosquittoBroker,
                                                                tmp_path: Path) -> None:
    async with vehicle(acl_broker, tmp_path, "drone1") as d1, \
            vehicle(acl_broker, tmp_path, "drone2") as d2, \
            ground_station(acl_broker, "companion/#", "g1", username="ground-drone1",
                           password=USERS["ground-drone1"]) as g1, \
            ground_station(acl_broker, "companion/#", "gf", username="ground-fleet",
                           password=USERS["ground-fleet"]) as fleet:
        # Its own vehicle: commanded and answered.
        await g1.client.publish("companion/drone1/cmd/vehicle", _cmd("g1-own"), qos=1)
        assert (await next_command(d1)).request_id == "g1-own"
        assert (await g1.wait_for(REPLY, lambda m: m["request_id"] == "g1-own"))["ok"]
        # Another vehicle: the broker drops it. A vehicle cannot command a peer either.
        await g1.client.publish("companion/drone2/cmd/vehicle", _cmd("g1-foreign"), qos=1)
        async with aiomqtt.Client(acl_broker.host, acl_broker.port, username="drone1",
                                  password=USERS["drone1"], identifier="rogue-d1") as rogue:
            await rogue.publish("companion/drone2/cmd/vehicle", _cmd("d1-foreign"), qos=1)
        # The configured fleet credential reaches drone2; it is the first command drone2 sees.
        await fleet.client.publish("companion/drone2/cmd/vehicle", _cmd("fleet-1"), qos=1)
        assert (await next_command(d2)).request_id == "fleet-1"
        await fleet.wait_for("companion/drone2/reply", lambda m: m["request_id"] == "fleet-1")
        assert d2.stats.commands_accepted == 1 and d2.stats.commands_rejected == 0
        # ground-drone1 reads nothing of drone2 (its retained online message included).
        await g1.wait_for("companion/drone1/online")
        assert not any(t.startswith("companion/drone2/") for t in g1.topics())
        assert "companion/drone2/online" in fleet.topics()
