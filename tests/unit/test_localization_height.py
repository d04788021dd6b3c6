"""The SLAM stage's height above the floor: the autopilot's, corrected by the floor the depth shows."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.service.localization import Localizer
from companion.sim.render import renderer_from_config
from companion.sim.sim_world import start_point_room_m
from companion.sources.sim import room_from_config
from semmap.frames import pose_from_xyz_rpy, rpy_from_rotation
from semmap.types import Frame


def _config() -> CompanionConfig:
    cfg = CompanionConfig()
    c = cfg.camera  # 320x240: a quarter of the pixels, the same view
    camera = c.model_copy(update={"width_px": c.width_px // 2, "height_px": c.height_px // 2, "fx_px": c.fx_px / 2,
                                  "fy_px": c.fy_px / 2, "cx_px": c.cx_px / 2, "cy_px": c.cy_px / 2})
    return cfg.model_copy(update={"camera": camera, "sim": cfg.sim.model_copy(update={"seed": 2, "layout": "realistic"})})


def _frames(cfg: CompanionConfig, height_error_m: float) -> list[tuple[Frame, float]]:
    """Frames on a short, turning track at about 0.8 m, posed with the autopilot's height
    ``height_error_m`` off the truth; with each, its true body height."""
    room = room_from_config(cfg)
    renderer = renderer_from_config(room, cfg)
    sx, sy = start_point_room_m(room)
    T_body_camera = cfg.camera.extrinsics.T_body_camera()
    out = []
    for i in range(12):
        z = 0.8 + 0.1 * math.sin(i / 3.0)
        yaw = 0.15 * i
        frame = renderer.render(pose_from_xyz_rpy(sx + 0.05 * i, sy, z, 0.0, 0.0, yaw) @ T_body_camera,
                                stamp_s=0.1 * i, index=i)
        posed = pose_from_xyz_rpy(0.05 * i, 0.0, z + height_error_m, 0.0, 0.0, yaw) @ T_body_camera
        out.append((replace(frame, T_map_camera=posed), z))
    return out


@pytest.mark.parametrize("height_error_m", [-0.12, 0.0, 0.15])
def test_px4_gps_denied_ekf_height_error_is_corrected_by_the_floor(height_error_m: float) -> None:
    # PX4 SITL's EKF2 (range finder and baro) held the height 0.1-0.15 m low in cruise: the
    # scanned band and the map's heights were off by as much.
    cfg = _config()
    loc = Localizer(cfg, cfg.camera.intrinsics())
    try:
        for frame, true_z in _frames(cfg, height_error_m):
            out = loc.localize(frame)
            assert out.T_map_camera is not None
            body = out.T_map_camera @ np.linalg.inv(cfg.camera.extrinsics.T_body_camera())
            assert body[2, 3] == pytest.approx(true_z, abs=0.02)
            roll, pitch, _ = rpy_from_rotation(body[:3, :3])
            assert abs(roll) < 1e-9 and abs(pitch) < 1e-9
    finally:
        loc.close()


def test_a_view_without_floor_keeps_the_last_correction() -> None:
    cfg = _config()
    loc = Localizer(cfg, cfg.camera.intrinsics())
    try:
        frame, true_z = _frames(cfg, -0.1)[0]
        loc.localize(frame)
        assert loc.floor_offset_m == pytest.approx(-0.1, abs=0.02)
        blank = replace(frame, depth_m=np.zeros_like(frame.depth_m))  # no valid depth: no floor
        out = loc.localize(blank)
        assert out.T_map_camera is not None
        body = out.T_map_camera @ np.linalg.inv(cfg.camera.extrinsics.T_body_camera())
        assert body[2, 3] == pytest.approx(true_z, abs=0.02)
    finally:
        loc.close()
