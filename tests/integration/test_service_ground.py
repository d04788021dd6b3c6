"""A goal sent over MQTT is flown by the service with the semantic planner, and answered."""

from __future__ import annotations

import asyncio
import json
import tempfile
from pathlib import Path

import aiomqtt
import numpy as np
import pytest
import yaml

from companion.config import load_config
from companion.service.app import CompanionService
from companion.service.mission_runner import position_enu
from companion.sim.demo_e2e import (
    crossing_waypoints_room,
    feasible_seed,
    free_udp_port,
    local_broker,
)
from companion.sim.sim_world import SimWorld

pytest.importorskip("open3d")

SMALL = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4},
}


def test_goal_over_mqtt_is_flown_and_answered(tmp_path: Path) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(SMALL))
    cfg = feasible_seed(load_config(path))
    link_port = free_udp_port()

    async def main() -> tuple[list[dict], np.ndarray, tuple[float, float]]:
        with tempfile.TemporaryDirectory() as tmp, local_broker(Path(tmp)) as broker:
            assert broker is not None
            c = cfg.model_copy(update={
                "mqtt": cfg.mqtt.model_copy(update={"port": broker.port}),
                "link": cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{link_port}"}),
                "service": cfg.service.model_copy(update={"output_dir": str(tmp_path / "out"),
                                                          "map_dir": str(tmp_path / "map")}),
            })
            world = SimWorld(c, autopilot_port=0, remote_ports=(link_port,))
            async with world:
                goal = world.placement.room_to_map_xy(crossing_waypoints_room(world.placement, c)[0])
                svc = CompanionService(c, world.frame_source(),
                                       object_classes={o.object_id: o.class_name for o in world.room.objects})
                stop = asyncio.Event()
                replies: list[dict] = []

                async def ground_station() -> None:
                    assert await asyncio.wait_for(_until_ground(svc), 30.0)
                    base = f"{c.mqtt.topic_prefix}/{c.mqtt.vehicle_id}"
                    async with aiomqtt.Client("127.0.0.1", broker.port) as client:
                        await client.subscribe(f"{base}/reply", qos=1)
                        await client.publish(f"{base}/cmd/goal", json.dumps(
                            {"schema_version": 1, "request_id": "g1", "x_m": goal[0], "y_m": goal[1]}), qos=1)
                        async with asyncio.timeout(90.0):
                            async for msg in client.messages:
                                replies.append(json.loads(bytes(msg.payload)))
                                if len(replies) == 2:
                                    break
                    stop.set()

                async with asyncio.TaskGroup() as tg:
                    tg.create_task(ground_station())
                    await svc.run(stop)
                assert svc.vehicle is not None
                pos = position_enu(svc.vehicle.snapshot())
                assert pos is not None
                return replies, pos, goal

    replies, pos, goal = asyncio.run(main())
    assert [r["request_id"] for r in replies] == ["g1", "g1"]
    assert all(r["ok"] for r in replies), replies
    assert np.linalg.norm(pos[:2] - np.array(goal)) < 0.35


async def _until_ground(svc: CompanionService) -> bool:
    for _ in range(300):
        if svc.ground is not None and svc.ground.connected and svc.state == "active":
            return True
        await asyncio.sleep(0.1)
    return False
