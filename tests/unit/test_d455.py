"""The D455 model: each depth and colour effect, switchable and seeded."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.sim.d455 import (
    ColorModel,
    DepthNoise,
    apply_color,
    apply_depth,
    exact_depth,
    exposure_gain,
    rotation_blur_px,
)
from companion.sim.render import RoomRenderer, renderer_from_config
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, pose_from_xyz_rpy
from tests.unit.test_render import CLASSES, HALF, camera_facing_east, empty_room

pytest.importorskip("open3d")

FX = 430.0


def _only(**effects: object) -> DepthNoise:
    return dataclasses.replace(exact_depth(min_m=0.0, max_m=6.0), **effects)  # type: ignore[arg-type]


def _gauss(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(shape[0] * shape[1]).astype(np.float32)


def test_default_noise_is_two_percent_rms_at_four_metres() -> None:
    r = RoomRenderer(empty_room(), CLASSES, HALF, noise=DepthNoise(), seed=2)
    frame = r.render(camera_facing_east(4.0, 3.0, 1.3))  # east wall 4 m ahead
    H, W = frame.depth_m.shape
    win = frame.depth_m[int(H * 0.3):int(H * 0.7), int(W * 0.3):int(W * 0.7)].astype(np.float64)
    valid = win[win > 0]
    assert valid.size > 0.95 * win.size
    assert float(np.sqrt(np.mean((valid - 4.0) ** 2))) / 4.0 == pytest.approx(0.02, rel=0.15)


def test_flying_pixels_fall_between_the_two_surfaces_of_an_edge() -> None:
    z = np.full((40, 60), 3.0, dtype=np.float32)
    z[:, :30] = 1.0
    rng = np.random.default_rng(0)
    off = apply_depth(z, _only(), rng, None, FX)
    assert set(np.unique(off).tolist()) == {1.0, 3.0}
    on = apply_depth(z, _only(flying_pixels=1.0), np.random.default_rng(0), None, FX)
    between = (on > 1.0) & (on < 3.0)
    assert between[:, 28:32].sum() > 60 and between[:, :28].sum() == 0 and between[:, 32:].sum() == 0


def test_dark_surfaces_lose_depth_and_bright_ones_keep_it() -> None:
    z = np.full((100, 100), 2.0, dtype=np.float32)
    albedo = np.full(z.shape, 0.8, dtype=np.float32)
    albedo[:, :50] = 0.03
    out = apply_depth(z, _only(dark_holes=0.8), np.random.default_rng(1), None, FX, albedo=albedo)
    dark_holes = float(np.mean(out[:, :50] == 0))
    assert dark_holes == pytest.approx(0.8 * (1 - 0.03 / 0.15), abs=0.05)
    assert np.all(out[:, 50:] == 2.0)


def test_shiny_surfaces_seen_head_on_lose_depth() -> None:
    z = np.full((100, 100), 2.0, dtype=np.float32)
    shiny = np.zeros(z.shape, dtype=bool)
    shiny[:, :50] = True
    out = apply_depth(z, _only(shiny_holes=0.7), np.random.default_rng(2), None, FX, shiny_head_on=shiny)
    assert float(np.mean(out[:, :50] == 0)) == pytest.approx(0.7, abs=0.05)
    assert np.all(out[:, 50:] == 2.0)


def test_minimum_range_scales_with_the_resolution() -> None:
    model = _only(min_z_m=0.5)
    assert model.effective_min_m(848) == pytest.approx(0.5)
    assert model.effective_min_m(424) == pytest.approx(0.25)
    wide = apply_depth(np.full((48, 848), 0.4, np.float32), model, np.random.default_rng(0), None, FX)
    narrow = apply_depth(np.full((24, 424), 0.4, np.float32), model, np.random.default_rng(0), None, FX)
    assert np.all(wide == 0.0) and np.all(narrow == pytest.approx(0.4))


def test_disparity_quantisation_steps_grow_with_range_squared() -> None:
    z = np.linspace(3.9, 4.1, 2000, dtype=np.float32).reshape(1, -1)
    out = apply_depth(z, _only(disparity_step_px=1 / 32), np.random.default_rng(0), None, FX)
    levels = np.unique(out)
    step = float(np.median(np.diff(levels)))
    assert step == pytest.approx(4.0**2 / (FX * 0.095) / 32, rel=0.1)


def test_holes_grow_towards_the_end_of_the_range() -> None:
    z = np.full((100, 100), 5.7, dtype=np.float32)
    out = apply_depth(z, _only(far_dropout=0.4), np.random.default_rng(3), None, FX)
    assert float(np.mean(out == 0)) == pytest.approx(0.4 * (5.7 - 4.5) / 1.5, abs=0.05)
    near = apply_depth(np.full((100, 100), 3.0, np.float32), _only(far_dropout=0.4), np.random.default_rng(3), None, FX)
    assert np.all(near > 0)


def test_the_same_generator_gives_the_same_depth() -> None:
    z = np.full((50, 80), 2.5, dtype=np.float32)
    z[10:30, 20:50] = 1.2
    albedo = np.full(z.shape, 0.1, dtype=np.float32)
    a = apply_depth(z, DepthNoise(), np.random.default_rng(5), _gauss(z.shape), FX, albedo=albedo)
    b = apply_depth(z, DepthNoise(), np.random.default_rng(5), _gauss(z.shape), FX, albedo=albedo)
    c = apply_depth(z, DepthNoise(), np.random.default_rng(6), _gauss(z.shape), FX, albedo=albedo)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_auto_exposure_brightens_dark_views_and_darkens_bright_ones() -> None:
    rng = np.random.default_rng(0)
    dark, bright = np.full((40, 40, 3), 40, np.uint8), np.full((40, 40, 3), 220, np.uint8)
    model = ColorModel(exposure_jitter=0.0)
    assert exposure_gain(dark, model, rng) > 1.3 and exposure_gain(bright, model, rng) < 0.8
    assert exposure_gain(dark, ColorModel(auto_exposure=False), rng) == 1.0
    assert float(apply_color(dark, 1.5, (0.0, 0.0)).mean()) == pytest.approx(60, abs=1)


def test_a_fast_yaw_turn_blurs_the_colour_image_sideways() -> None:
    # 60 deg/s about the camera's vertical (optical y) axis for 1/15 s.
    R0 = np.eye(3)
    a = math.radians(60) / 15
    R1 = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    du, dv = rotation_blur_px(R0, R1, 1 / 15, 383.0, 0.012)
    assert abs(du) == pytest.approx(383.0 * math.radians(60) * 0.012, rel=0.01) and abs(dv) < 1e-6

    cfg = CompanionConfig()
    still = renderer_from_config(empty_room(), cfg.model_copy(update={"sim": cfg.sim.model_copy(
        update={"rgb_motion_blur": False})}))
    moving = renderer_from_config(empty_room(), cfg)
    T0 = pose_from_xyz_rpy(4.0, 3.0, 1.2, 0.0, math.radians(40), 0.0) @ make_transform(R_BODY_CAMERA_FORWARD, np.zeros(3))
    T1 = pose_from_xyz_rpy(4.0, 3.0, 1.2, 0.0, math.radians(40), math.radians(6)) @ make_transform(
        R_BODY_CAMERA_FORWARD, np.zeros(3))

    def sharpness(rgb: np.ndarray) -> float:
        g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        return float(np.abs(np.diff(g, axis=1)).mean())

    for r in (still, moving):
        r.render(T0, stamp_s=0.0, index=0)
    s_still = sharpness(still.render(T1, stamp_s=0.1, index=1).rgb)
    s_moving = sharpness(moving.render(T1, stamp_s=0.1, index=1).rgb)
    assert s_moving < 0.8 * s_still
