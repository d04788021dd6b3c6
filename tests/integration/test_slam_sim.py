"""SLAM on a rendered flight through a furnished room with a drifting autopilot."""

from __future__ import annotations

import math

import numpy as np

from companion.sim.odometry import OdometryDriftModel
from companion.sim.render import RoomRenderer
from companion.sim.trajectory import fly_route, plan_route
from companion.sim.world import generate_room
from semmap.config import ExtrinsicsConfig, SlamConfig, default_classes
from semmap.costmap import VerticalBand
from semmap.slam import Slam2D, level_scan_from_depth
from semmap.types import CameraIntrinsics


def test_slam_error_is_smaller_than_the_drifting_odometry() -> None:
    room = generate_room(3, n_objects=8)
    altitude = 0.6
    band = VerticalBand.for_altitude(altitude, 0.3, 0.1)
    w, d, inset = room.width_m, room.depth_m, 1.0
    route = plan_route(room, [(inset, inset), (w - inset, inset), (w - inset, d - inset)], altitude, 0.4,
                       largest_component_only=True)
    traj = fly_route(route, altitude, 0.5, yaw_rate_max_rad_s=math.radians(90.0),
                     yaw_sweep_rad=math.radians(40.0), sweep_period_s=6.0)
    intr = CameraIntrinsics(95.75, 95.75, 80.0, 60.0, 160, 120)
    renderer = RoomRenderer(room, [c.name for c in default_classes()], intr, seed=3)
    T_body_camera = ExtrinsicsConfig().T_body_camera()
    drift = OdometryDriftModel(0.03, 0.5, seed=3)
    rate_hz = 6.0
    truth, odom, est = [], [], []
    with Slam2D(SlamConfig(), background=False) as slam:
        for i in range(int(min(traj.duration_s, 25.0) * rate_hz)):
            t = i / rate_hz
            xyz, yaw = traj.state_at(t)
            frame = renderer.render(traj.T_map_body(t) @ T_body_camera, stamp_s=t, index=i)
            scan = level_scan_from_depth(frame.depth_m, intr, T_body_camera, 0.0, 0.0, float(xyz[2]), band,
                                         stride_px=1, stamp_s=t)
            o = drift.update(t, (xyz[0], xyz[1], yaw))
            est.append(slam.add_scan(t, scan, o).pose_map)
            truth.append((xyz[0], xyz[1]))
            odom.append(o)
    truth_a = np.array(truth)

    def ate(a: list[np.ndarray]) -> float:
        return float(np.sqrt(np.mean(np.sum((np.array(a)[:, :2] - truth_a) ** 2, axis=1))))

    assert ate(odom) > 0.15
    assert ate(est) < 0.6 * ate(odom)
