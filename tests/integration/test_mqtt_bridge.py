"""The MQTT ground link against a real Mosquitto broker on loopback.

A second aiomqtt client plays the ground station. Covered: state and commands round trip,
invalid commands answered and never delivered, the broker restarted under the bridge,
password file + ACL (good and bad credentials) and TLS.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiomqtt
import numpy as np
import pytest
from mosquitto_broker import MosquittoBroker, TlsFiles, make_tls_files

from companion.config import MqttConfig
from companion.errors import GroundLinkError
from companion.ground import CommandValidator, GoalCommand, MissionCommand, MqttBridge
from companion.ground.messages import (
    MapMessage,
    ObjectsMessage,
    OnlineMessage,
    PathMessage,
    ReplyMessage,
    StatusMessage,
    TelemetryMessage,
    decode_cost_png,
)
from semmap.costmap import LETHAL_OBSTACLE, NO_INFORMATION, Costmap, ObjectFootprint, VerticalBand
from semmap.grid import GridSpec

pytestmark = pytest.mark.asyncio

VEHICLE = "drone1"
BASE = f"companion/{VEHICLE}"
WAIT_S = 15.0  # generous: the test machine is shared; nothing here measures time


# --- helpers ------------------------------------------------------------------------------

def mqtt_cfg(broker: MosquittoBroker, **kw: Any) -> MqttConfig:
    base: dict[str, Any] = dict(
        host=broker.host, port=broker.port, vehicle_id=VEHICLE, topic_prefix="companion",
        reconnect_min_s=0.1, reconnect_max_s=0.5, keepalive_s=5, timeout_s=5.0,
    )
    base.update(kw)
    return MqttConfig(**base)


def validator(rate_limit_hz: float = 50.0, burst: int = 50) -> CommandValidator:
    return CommandValidator(
        geofence_xy_m=(0.0, 0.0, 8.0, 6.0), max_altitude_m=3.0,
        rate_limit_hz=rate_limit_hz, burst=burst,
    )


def footprint(object_id: int, x_m: float) -> ObjectFootprint:
    poly = np.array([[x_m, 1.0], [x_m + 1.2, 1.0], [x_m + 1.2, 1.8], [x_m, 1.8]])  # (4, 2)
    return ObjectFootprint(object_id, "desk", poly, 0.0, 0.75, existence=0.9, margin_m=0.25)


class Ground:
    """A ground station: records everything under the vehicle's base topic."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.received: list[tuple[str, bytes, bool]] = []
        self._new = asyncio.Event()

    async def pump(self) -> None:
        async for m in self.client.messages:
            payload = m.payload if isinstance(m.payload, bytes) else str(m.payload).encode()
            self.received.append((m.topic.value, payload, bool(m.retain)))
            self._new.set()

    def messages(self, suffix: str) -> list[dict[str, Any]]:
        return [json.loads(p) for t, p, _ in self.received if t == f"{BASE}/{suffix}"]

    async def wait_for(
        self, suffix: str, pred: Callable[[dict[str, Any]], bool] = lambda m: True
    ) -> dict[str, Any]:
        """The first message on ``<base>/<suffix>`` satisfying ``pred`` (waits for it)."""
        async def _wait() -> dict[str, Any]:
            while True:
                for m in self.messages(suffix):
                    if pred(m):
                        return m
                self._new.clear()
                await self._new.wait()
        try:
            return await asyncio.wait_for(_wait(), WAIT_S)
        except asyncio.TimeoutError:
            topics = sorted({t for t, _, _ in self.received})
            pytest.fail(f"no matching message on {BASE}/{suffix}; received topics: {topics}")

    async def reply_to(self, request_id: str) -> dict[str, Any]:
        return await self.wait_for("reply", lambda m: m["request_id"] == request_id)

    async def send(self, kind: str, payload: dict[str, Any] | str | bytes, retain: bool = False) -> None:
        data = payload if isinstance(payload, (str, bytes)) else json.dumps(payload)
        await self.client.publish(f"{BASE}/cmd/{kind}", data, qos=1, retain=retain)


@contextlib.asynccontextmanager
async def ground_station(
    broker: MosquittoBroker, *, username: str | None = None, password: str | None = None,
    tls_context: Any = None,
) -> AsyncIterator[Ground]:
    async with aiomqtt.Client(
        broker.host, broker.port, username=username, password=password,
        identifier=f"ground-{id(broker)}", tls_context=tls_context,
    ) as client:
        await client.subscribe(f"{BASE}/#", qos=1)
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


async def until(cond: Callable[[], bool], what: str) -> None:
    """Poll ``cond`` (a plain predicate on the bridge's state) until it holds."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + WAIT_S
    while loop.time() < deadline:
        if cond():
            return
        await asyncio.sleep(0.02)
    pytest.fail(f"timed out waiting for: {what}")


@pytest.fixture
def broker(tmp_path: Path) -> Any:
    b = MosquittoBroker(tmp_path / "broker").start()
    yield b
    b.stop()


# --- tests --------------------------------------------------------------------------------

async def test_state_and_commands_round_trip(broker: MosquittoBroker) -> None:
    spec = GridSpec(0.05, (-1.0, -2.0), (40, 60))
    cost = np.zeros(spec.shape_rc, dtype=np.uint8)
    cost[5:9, 10:30] = LETHAL_OBSTACLE
    cost[30:, :] = NO_INFORMATION
    costmap = Costmap(spec, cost, VerticalBand(0.4, 0.8), stamp_s=1234.5)

    async with ground_station(broker) as ground, \
            MqttBridge(mqtt_cfg(broker), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        online = OnlineMessage.model_validate(await ground.wait_for("online"))
        assert online.online and online.vehicle_id == VEHICLE

        assert bridge.publish_status("mapping", 12.5, {"perception": 41.23}, {"mavlink": True})
        assert bridge.publish_telemetry([1.0, 2.0, 0.6], [0.1, 0.0, 0.0], np.pi / 2, True, True,
                                        "OFFBOARD", 87.0)
        assert bridge.publish_objects([footprint(3, 2.0), footprint(1, 4.0)])
        assert not bridge.publish_objects([footprint(1, 4.0), footprint(3, 2.0)])  # unchanged
        assert bridge.publish_path([[0.5, 0.5, 0.6], [3.5, 4.5, 0.6]], request_id="g-1")
        bridge.publish_map(costmap)

        status = StatusMessage.model_validate(await ground.wait_for("status"))
        assert status.state == "mapping" and status.stage_timings_ms == {"perception": 41.2}
        tel = TelemetryMessage.model_validate(await ground.wait_for("telemetry"))
        assert tel.xyz_map_m == (1.0, 2.0, 0.6) and tel.yaw_deg == pytest.approx(90.0)
        objs = ObjectsMessage.model_validate(await ground.wait_for("objects"))
        assert [o.object_id for o in objs.objects] == [1, 3]
        assert objs.objects[1].polygon_xy_m[1] == (3.2, 1.0)
        path = PathMessage.model_validate(await ground.wait_for("path"))
        assert path.length_m == pytest.approx(5.0) and path.request_id == "g-1"
        mp = MapMessage.model_validate(await ground.wait_for("map"))
        assert (mp.width_px, mp.height_px, mp.origin_xy_m) == (60, 40, (-1.0, -2.0))
        np.testing.assert_array_equal(decode_cost_png(base64.b64decode(mp.png_base64)), cost)
        assert len(ground.messages("objects")) == 1  # the unchanged list was not sent again

        await ground.send("goal", {"schema_version": 1, "request_id": "g-2", "x_m": 3.0,
                                   "y_m": 4.0, "altitude_m": 1.2, "yaw_deg": 45.0})
        cmd = await next_command(bridge)
        assert cmd == GoalCommand(schema_version=1, request_id="g-2", x_m=3.0, y_m=4.0,
                                  altitude_m=1.2, yaw_deg=45.0)
        reply = ReplyMessage.model_validate(await ground.reply_to("g-2"))
        assert reply.ok and reply.command == "goal" and reply.reason is None

        await ground.send("mission", {"schema_version": 1, "request_id": "m-1", "action": "pause"})
        assert await next_command(bridge) == MissionCommand(
            schema_version=1, request_id="m-1", action="pause")

    # A graceful close says so on the retained online topic.
    async with ground_station(broker) as late:
        assert (await late.wait_for("online"))["online"] is False


async def test_invalid_commands_are_answered_and_never_delivered(broker: MosquittoBroker) -> None:
    bad: list[tuple[str, str | dict[str, Any], str]] = [
        ("goal", '{"schema_version": 1, "request_id": "b-1", "x_m": 1.0,', "not valid JSON"),
        ("goal", {"schema_version": 1, "request_id": "b-2", "x_m": 1.0, "y_m": 1.0,
                  "speed": 3}, "goal.speed: unknown field"),
        ("goal", {"schema_version": 1, "request_id": "b-3", "x_m": 20.0, "y_m": 1.0},
         "goal.x_m: 20.0 is outside the geofence"),
        ("goal", {"schema_version": 1, "request_id": "b-4", "x_m": 1.0, "y_m": 1.0,
                  "altitude_m": 12}, "goal.altitude_m: must be <= 3.0 (got 12"),
        ("goal", {"schema_version": 1, "request_id": "b-5", "x_m": "1", "y_m": 1.0},
         "goal.x_m: must be a number"),
        ("mission", {"schema_version": 1, "request_id": "b-6", "action": "fly"},
         "mission.action: must be one of"),
        ("vehicle", {"schema_version": 2, "request_id": "b-7", "action": "land"},
         "vehicle.schema_version"),
        ("goal", '{"schema_version": 1, "request_id": "b-8", "x_m": NaN, "y_m": 1.0}',
         "goal.x_m: must be a finite number"),
    ]
    async with ground_station(broker) as ground:
        # A retained command would run again at every reconnect: the bridge must refuse it.
        await ground.send("vehicle", {"schema_version": 1, "request_id": "r-1", "action": "land"},
                          retain=True)
        async with MqttBridge(mqtt_cfg(broker), validator()) as bridge:
            assert await bridge.wait_connected(WAIT_S)
            await _send_and_check(ground, bridge, bad)
        await ground.client.publish(f"{BASE}/cmd/vehicle", b"", qos=1, retain=True)  # clear


async def _send_and_check(
    ground: Ground, bridge: MqttBridge, bad: list[tuple[str, str | dict[str, Any], str]]
) -> None:
    for kind, payload, _ in bad:
        await ground.send(kind, payload)
    await ground.send("vehicle", {"schema_version": 1, "request_id": "ok-1", "action": "hold"})
    for i, (kind, _, reason) in enumerate(bad):
        rid = f"b-{i + 1}"
        if rid == "b-1":  # unreadable JSON: no request_id to echo
            reply = await ground.wait_for("reply", lambda m: "not valid JSON" in (m["reason"] or ""))
        else:
            reply = await ground.reply_to(rid)
        assert reply["ok"] is False and reply["command"] == kind
        assert reason in reply["reason"], (rid, reply["reason"])
    retained = await ground.reply_to("r-1")
    assert retained["ok"] is False and "retained" in retained["reason"]
    # The only command that reaches the service is the valid one sent last.
    cmd = await next_command(bridge)
    assert cmd.request_id == "ok-1" and cmd.action == "hold"
    assert bridge.stats.commands_rejected == len(bad) + 1
    assert bridge.stats.commands_accepted == 1


async def test_rate_limited_commands_are_refused(broker: MosquittoBroker) -> None:
    # 0.01 Hz with a burst of 2: exactly two of five commands pass, whatever the timing.
    async with ground_station(broker) as ground, \
            MqttBridge(mqtt_cfg(broker), validator(rate_limit_hz=0.01, burst=2)) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        for i in range(5):
            await ground.send("mission", {"schema_version": 1, "request_id": f"m-{i}",
                                          "action": "start"})
        replies = [await ground.reply_to(f"m-{i}") for i in range(5)]
        assert [r["ok"] for r in replies] == [True, True, False, False, False]
        assert all("rate limited" in r["reason"] for r in replies[2:])
        assert (await next_command(bridge)).request_id == "m-0"
        assert (await next_command(bridge)).request_id == "m-1"


async def test_broker_restart_reconnects_and_republishes_latest_state(
    broker: MosquittoBroker, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="companion.ground")
    async with MqttBridge(mqtt_cfg(broker), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        bridge.publish_objects([footprint(1, 1.0)])
        bridge.publish_path([[0.5, 0.5, 0.6], [1.5, 0.5, 0.6]])
        async with ground_station(broker) as ground:
            await ground.wait_for("objects")

        broker.stop()
        await until(lambda: not bridge.connected, "the bridge notices the broker is gone")
        # The service keeps going while the broker is down: publishing still works.
        assert bridge.publish_objects([footprint(1, 1.0), footprint(2, 5.0)])
        assert bridge.publish_path([[0.5, 0.5, 0.6], [6.5, 0.5, 0.6]])
        assert bridge.publish_telemetry([6.0, 0.5, 0.6], [0.0, 0.0, 0.0], 0.0, True, True, "OFFBOARD")
        await until(lambda: bridge.stats.connect_failures >= 2, "reconnect attempts with backoff")
        assert isinstance(bridge.last_error, GroundLinkError)

        broker.start()  # same port, persistence off: the broker lost every retained message
        assert await bridge.wait_connected(WAIT_S)
        async with ground_station(broker) as ground:
            objs = await ground.wait_for("objects")
            assert [o["object_id"] for o in objs["objects"]] == [1, 2]
            path = await ground.wait_for("path")
            assert path["waypoints_xyz_map_m"][-1] == [6.5, 0.5, 0.6]
            assert (await ground.wait_for("online"))["online"] is True
            await ground.send("vehicle", {"schema_version": 1, "request_id": "h-1",
                                          "action": "hold"})
            assert (await next_command(bridge)).request_id == "h-1"
        assert bridge.stats.disconnects >= 1 and bridge.stats.connects >= 2
        assert any("ground link down" in r.getMessage() for r in caplog.records)


ACL = f"""\
user vehicle
topic write {BASE}/+
topic read {BASE}/cmd/#

user ground
topic read {BASE}/#
topic write {BASE}/cmd/#
"""


@pytest.fixture
def secured_broker(tmp_path: Path) -> Any:
    b = MosquittoBroker(
        tmp_path / "secured", passwords={"vehicle": "v-secret", "ground": "g-secret"}, acl=ACL
    ).start()
    yield b
    b.stop()


async def test_password_and_acl_good_credentials(secured_broker: MosquittoBroker, tmp_path: Path) -> None:
    pw = tmp_path / "vehicle.password"
    pw.write_text("v-secret\n")
    cfg = mqtt_cfg(secured_broker, username="vehicle", password_file=str(pw))
    async with ground_station(secured_broker, username="ground", password="g-secret") as ground, \
            MqttBridge(cfg, validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        bridge.publish_status("idle", 1.0)
        assert (await ground.wait_for("status"))["state"] == "idle"
        await ground.send("goal", {"schema_version": 1, "request_id": "a-1", "x_m": 1.0,
                                   "y_m": 2.0})
        assert (await next_command(bridge)).request_id == "a-1"
        assert (await ground.reply_to("a-1"))["ok"] is True


async def test_bad_credentials_retry_without_crashing(
    secured_broker: MosquittoBroker, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="companion.ground")
    pw = tmp_path / "wrong.password"
    pw.write_text("not-the-password\n")
    cfg = mqtt_cfg(secured_broker, username="vehicle", password_file=str(pw))
    async with MqttBridge(cfg, validator()) as bridge:
        await until(lambda: bridge.stats.connect_failures >= 3, "three refused attempts")
        assert not bridge.connected
        assert isinstance(bridge.last_error, GroundLinkError)
        assert "refused user 'vehicle'" in str(bridge.last_error)
        assert "mqtt.password_file" in str(bridge.last_error)
        assert bridge.publish_status("idle", 1.0)  # the service carries on
    assert any("refused user 'vehicle'" in r.getMessage() for r in caplog.records)


async def test_missing_password_file_is_a_clear_error(broker: MosquittoBroker, tmp_path: Path) -> None:
    cfg = mqtt_cfg(broker, username="vehicle", password_file=str(tmp_path / "nope"))
    with pytest.raises(GroundLinkError, match=r"mqtt.password_file: cannot read .*nope"):
        async with MqttBridge(cfg, validator()):
            pass


@pytest.fixture
def tls_files(tmp_path: Path) -> TlsFiles:
    return make_tls_files(tmp_path, "broker")


async def test_tls_listener(tls_files: TlsFiles, tmp_path: Path,
                            caplog: pytest.LogCaptureFixture) -> None:
    import ssl

    b = MosquittoBroker(tmp_path / "tls", tls=tls_files).start()
    try:
        ground_ctx = ssl.create_default_context(cafile=str(tls_files.ca_cert))
        cfg = mqtt_cfg(b, tls_ca_file=str(tls_files.ca_cert))
        async with ground_station(b, tls_context=ground_ctx) as ground, \
                MqttBridge(cfg, validator()) as bridge:
            assert await bridge.wait_connected(WAIT_S)
            bridge.publish_status("tls-ok", 2.0)
            assert (await ground.wait_for("status"))["state"] == "tls-ok"

        # A broker whose certificate our CA did not sign is refused, and retried.
        other_ca = make_tls_files(tmp_path, "other").ca_cert
        caplog.set_level(logging.WARNING, logger="companion.ground")
        async with MqttBridge(mqtt_cfg(b, tls_ca_file=str(other_ca)), validator()) as bridge:
            await until(lambda: bridge.stats.connect_failures >= 2, "refused TLS handshakes")
            assert not bridge.connected
            assert "CERTIFICATE_VERIFY_FAILED" in str(bridge.last_error).upper().replace(" ", "_")
    finally:
        b.stop()


async def test_outbox_drops_oldest_events_and_logs(tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="companion.ground")
    down = MosquittoBroker(tmp_path / "down")  # configured, never started: nobody listens
    async with MqttBridge(mqtt_cfg(down, outbox_size=10), validator()) as bridge:
        for i in range(25):
            bridge.publish_reply("goal", False, f"x-{i}", "test")
        for _ in range(50):
            bridge.publish_telemetry([0, 0, 0], [0, 0, 0], 0.0, False, False, "HOLD")
        assert not bridge.publish_telemetry([np.nan, 0, 0], [0, 0, 0], 0.0, False, False, "HOLD")
        assert bridge.stats.dropped_events == 15
    drops = [r for r in caplog.records if "outbox full" in r.getMessage()]
    assert len(drops) == 15
    assert any("not publishing telemetry" in r.getMessage() for r in caplog.records)


async def test_a_full_command_queue_refuses_instead_of_queueing(broker: MosquittoBroker) -> None:
    async with ground_station(broker) as ground, \
            MqttBridge(mqtt_cfg(broker, command_queue_size=1), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        for i in range(2):  # nobody consumes commands meanwhile
            await ground.send("vehicle", {"schema_version": 1, "request_id": f"q-{i}",
                                          "action": "hold"})
        assert (await ground.reply_to("q-0"))["ok"] is True
        busy = await ground.reply_to("q-1")
        assert busy["ok"] is False and busy["reason"].startswith("service busy")
        assert (await next_command(bridge)).request_id == "q-0"


async def test_empty_and_foreign_messages_are_ignored_quietly() -> None:
    bridge = MqttBridge(MqttConfig(vehicle_id=VEHICLE), validator())
    bridge.handle_message(f"{BASE}/cmd/goal", b"")  # how MQTT clears a retained message
    bridge.handle_message(f"{BASE}/status", b"{}")  # not a command topic
    bridge.handle_message(f"{BASE}/cmd/goal", 12345)  # not bytes at all: refused, no raise
    assert bridge.stats.commands_rejected == 1 and bridge.stats.commands_accepted == 0


async def test_map_goes_out_at_a_low_rate_newest_first(broker: MosquittoBroker) -> None:
    spec = GridSpec(0.1, (0.0, 0.0), (20, 30))

    def costmap(stamp_s: float) -> Costmap:
        return Costmap(spec, np.zeros(spec.shape_rc, np.uint8), VerticalBand(0.4, 0.8), stamp_s)

    async with ground_station(broker) as ground, \
            MqttBridge(mqtt_cfg(broker, map_rate_hz=2.0), validator()) as bridge:
        assert await bridge.wait_connected(WAIT_S)
        bridge.publish_map(costmap(1.0))
        await ground.wait_for("map", lambda m: m["map_stamp_s"] == 1.0)
        bridge.publish_map(costmap(2.0))  # superseded before its turn comes
        bridge.publish_map(costmap(3.0))
        await ground.wait_for("map", lambda m: m["map_stamp_s"] == 3.0)
        assert [m["map_stamp_s"] for m in ground.messages("map")] == [1.0, 3.0]


async def test_from_config_takes_limits_from_the_planner() -> None:
    from companion.config import CompanionConfig
    from planner.config import PlannerConfig

    cfg = CompanionConfig(planner=PlannerConfig(geofence_xy_m=(0, 0, 4, 4), max_altitude_m=2.0),
                          mqtt=MqttConfig(vehicle_id="d9", command_burst=2))
    bridge = MqttBridge.from_config(cfg)
    assert bridge.topics.base == "companion/d9"
    assert bridge.validator.fence_xy_m == (0, 0, 4, 4) and bridge.validator.max_altitude_m == 2.0
