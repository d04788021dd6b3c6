"""The MQTT ground link's close against a real Mosquitto broker, while its send loop is busy.

aiomqtt's publish waits for its acknowledgement with ``asyncio.wait_for``; on Python 3.11 a
cancellation delivered once that acknowledgement has arrived is swallowed, and the send loop
runs on. A close that awaited the loop once then never ended (a quarter to three quarters of
the closes here, on a loaded machine).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from mosquitto_broker import MosquittoBroker

from companion.config import MqttConfig
from companion.ground import CommandValidator, MqttBridge
from companion.ground.bridge import _Outgoing

pytestmark = pytest.mark.asyncio

CLOSES = 30
#: Far beyond a close's normal few milliseconds, far below a hung one's forever.
CLOSE_BOUND_S = 8.0


@pytest.fixture
def broker(tmp_path: Path) -> Any:
    b = MosquittoBroker(tmp_path / "broker").start()
    yield b
    b.stop()


def _bridge(broker: MosquittoBroker) -> MqttBridge:
    cfg = MqttConfig(host=broker.host, port=broker.port, vehicle_id="close1", reconnect_min_s=0.1,
                     reconnect_max_s=0.5, keepalive_s=5, timeout_s=5.0)
    validator = CommandValidator(geofence_xy_m=(0.0, 0.0, 8.0, 6.0), max_altitude_m=3.0, rate_limit_hz=50.0, burst=50)
    return MqttBridge(cfg, validator)


async def test_bridge_close_ends_while_its_send_loop_waits_for_an_acknowledgement_python311_wait_for(
        broker: MosquittoBroker) -> None:
    hung: list[int] = []
    for i in range(CLOSES):
        bridge = _bridge(broker)
        await bridge.__aenter__()
        assert await bridge.wait_connected(5.0)
        # A backlog of state and events, as the status loop leaves it when the service stops; a
        # QoS 0 event's acknowledgement is its socket write, one loop iteration after the publish.
        for k in range(3):
            bridge.publish_telemetry((0.01 * k, 0.0, 1.0), (0.0, 0.0, 0.0), 0.0, True, True, "OFFBOARD", 80.0)
            bridge.publish_status("stopping", float(k))
            bridge._put_event(_Outgoing(f"{bridge.topics.base}/probe", b"{}", 0, False))
            bridge.publish_reply("goal", False, f"r{i}-{k}", "stopping")
            await asyncio.sleep(0)
        closing = asyncio.create_task(bridge.__aexit__(None, None, None))
        done, _ = await asyncio.wait({closing}, timeout=CLOSE_BOUND_S)
        if closing not in done:
            hung.append(i)
        left = [t for t in asyncio.all_tasks() if t.get_name().startswith("mqtt-")]
        for t in left:  # a hung close's loops, so the next round starts clean
            t.cancel()
        if closing not in done:
            closing.cancel()
        await asyncio.gather(*left, closing, return_exceptions=True)
        if hung:
            break
    assert not hung, f"close {hung[0]} of the ground link did not end within {CLOSE_BOUND_S:.0f} s"
