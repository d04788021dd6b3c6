"""The safety bench's closed loop (bench/_safety_loop.py): MAVLink into the lock-step mock PX4,
and one room flown with the metric-only and the semantic map."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bench._judge import judge_flight
from bench._safety_loop import HOME, LockstepAutopilot, LockstepFlight, _CompanionLink
from bench._safety_scenarios import make_scenarios
from companion import px4
from companion.config import CompanionConfig
from companion.mavlink.failsafe import PositionSetpoint
from companion.mavlink.offboard import encode_setpoint
from companion.sim.groundtruth import clearance_m
from companion.sim.render import renderer_from_config
from semmap.detection import detector_from_config


def test_lockstep_autopilot_flies_offboard_setpoints_sent_as_mavlink() -> None:
    ap = LockstepAutopilot(0.0, seed=0)
    link = _CompanionLink(ap.now_s)

    def send(msg: object) -> None:
        ap.receive(msg.pack(link.mav))  # type: ignore[attr-defined]

    def command(cmd: int, *p: float) -> int:
        send(link.mav.command_long_encode(1, 1, cmd, 0, *[*p, *([0.0] * (7 - len(p)))]))
        return int(ap.commands.history[-1].result)  # type: ignore[arg-type]

    assert command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    assert command(mavlink.MAV_CMD_NAV_TAKEOFF, *([float("nan")] * 6), HOME.alt_m + 1.0) == mavlink.MAV_RESULT_ACCEPTED
    for _ in range(500):
        ap.advance(0.01)
    assert -ap.vehicle.position_ned_m[2] == pytest.approx(1.0, abs=0.1)
    # Offboard is refused without a setpoint stream, accepted with one, and flies it.
    assert command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(px4.FlightMode.OFFBOARD)) != \
        mavlink.MAV_RESULT_ACCEPTED
    sp = PositionSetpoint((2.0, 1.0, -1.0), yaw_rad=0.0)
    for k in range(600):
        if k % 3 == 0:
            send(encode_setpoint(link, sp, 1, 1))  # type: ignore[arg-type]
        if k == 30:
            assert command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(px4.FlightMode.OFFBOARD)) == \
                mavlink.MAV_RESULT_ACCEPTED
        ap.advance(0.01)
    assert ap.mode is px4.FlightMode.OFFBOARD
    assert np.allclose(ap.vehicle.position_ned_m, (2.0, 1.0, -1.0), atol=0.1)


@pytest.mark.slow
def test_semantic_map_flies_around_the_chair_the_depth_slice_misses() -> None:
    cfg = CompanionConfig()
    # Scattered: one known room where a lone chair stands on the straight line; realistic rooms
    # are flown by bench/safety.py. Its goal stands a metre from everything: the test is about
    # the chair on the line, not about a neighbour's early footprint moving the goal.
    sc = make_scenarios(cfg, 1, 1034, [0.6], layout="scattered")[0]
    assert sc.kind == "blocking"
    assert {cls for _, cls in sc.crossed} == {"chair"}
    # Everything from the floor up to 1.2 m (twice the altitude) is more than a metre from the goal.
    assert clearance_m(sc.room, np.array([[*sc.goal_xy_m, sc.altitude_m]]), vehicle_height_m=1.2)[0] > 1.0
    p = cfg.planner
    renderer = renderer_from_config(sc.room, cfg.model_copy(update={"sim": cfg.sim.model_copy(
        update={"seed": sc.room.seed})}))
    verdicts = {}
    try:
        for mode in ("metric", "semantic"):
            det = detector_from_config(cfg.detector.model_copy(update={"kind": "oracle"}), [c.name for c in cfg.classes],
                                       object_classes={o.object_id: o.class_name for o in sc.room.objects},
                                       seed=sc.room.seed)
            # A fixed compute time per frame and plan: the flight does not depend on how busy the
            # machine running the tests is.
            flight = LockstepFlight(cfg, sc, mode, det, "oracle", renderer, perception_hz=4.0, time_limit_s=30.0,
                                    compute_s=0.05)
            log = flight.run()
            assert log.error is None
            xyz, t = flight.trajectory_room()
            verdicts[mode] = judge_flight(sc.room, xyz, t, sc.goal_xy_m, vehicle_radius_m=p.vehicle_radius_m,
                                          vehicle_height_m=p.vehicle_height_m,
                                          vertical_margin_m=p.vertical_margin_m, acceptance_m=0.3,
                                          time_limit_s=30.0)
    finally:
        renderer.close()
    crossed = {i for i, _ in sc.crossed}
    # The metric-only map (a thin slice at 0.6 m) has the seat's legs and backrest only: the
    # straight path runs under the seat, closer than the vertical margin.
    assert verdicts["metric"].collided and set(verdicts["metric"].hit_object_ids) & crossed
    assert verdicts["semantic"].reached and not verdicts["semantic"].collided
