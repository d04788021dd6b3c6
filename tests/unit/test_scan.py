"""The depth band scan: hits at the right place, band filtering, invalid depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.costmap import VerticalBand
from semmap.errors import FrameError
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, rotation_from_rpy
from semmap.scan import extract_band_scan
from semmap.types import CameraIntrinsics

K = CameraIntrinsics(200.0, 200.0, 80.0, 60.0, 160, 120)


def camera_pose(x: float, y: float, z: float, yaw_rad: float = 0.0, pitch_rad: float = 0.0) -> np.ndarray:
    """Camera looking along map +x rotated by yaw, tilted down by pitch."""
    return make_transform(rotation_from_rpy(0.0, pitch_rad, yaw_rad) @ R_BODY_CAMERA_FORWARD, np.array([x, y, z]))


def wall_depth(distance_m: float, T: np.ndarray, wall_x_m: float) -> np.ndarray:
    """Depth image of the vertical plane x = wall_x_m for a camera at pose T (ray casting)."""
    u, v = np.meshgrid(np.arange(K.width_px), np.arange(K.height_px))
    d_cam = np.stack([(u - K.cx_px) / K.fx_px, (v - K.cy_px) / K.fy_px, np.ones_like(u, float)], -1)
    d_map = d_cam @ T[:3, :3].T
    t = (wall_x_m - T[0, 3]) / d_map[..., 0]
    return np.where(t > 0, t, 0.0).astype(np.float32)


def test_wall_ahead_gives_hits_at_its_distance() -> None:
    T = camera_pose(1.0, 2.0, 0.6)
    depth = np.full((K.height_px, K.width_px), 3.0, np.float32)  # fronto-parallel wall at 3 m
    scan = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8), stride_px=1)
    assert scan.n_rays == K.width_px
    assert scan.is_hit.all() and scan.valid.all()
    assert np.allclose(scan.hits_xy_m[:, 0], 4.0, atol=1e-4)
    half_width = 3.0 * K.cx_px / K.fx_px
    assert scan.hits_xy_m[:, 1].min() == pytest.approx(2.0 - half_width, abs=0.02)
    assert scan.hits_xy_m[:, 1].max() == pytest.approx(2.0 + half_width * (K.width_px - 1 - K.cx_px) / K.cx_px, abs=0.02)
    assert np.allclose(scan.near_xy_m, [1.0, 2.0])
    assert np.all((scan.hit_z_m >= 0.4) & (scan.hit_z_m <= 0.8))


def test_yawed_and_pitched_camera_puts_the_wall_in_the_right_place() -> None:
    T = camera_pose(0.0, 0.0, 0.7, yaw_rad=math.radians(20), pitch_rad=math.radians(10))
    depth = wall_depth(2.5, T, wall_x_m=2.5)
    scan = extract_band_scan(depth, K, T, VerticalBand(0.5, 0.9), stride_px=1)
    assert scan.is_hit.sum() > 0.9 * scan.n_rays
    assert np.allclose(scan.hits_xy_m[:, 0], 2.5, atol=1e-3)


def test_band_filtering_ignores_obstacles_outside_the_band() -> None:
    T = camera_pose(0.0, 0.0, 0.6)
    # A table top: every pixel below the horizon sees a horizontal plane at z = 0.45.
    u, v = np.meshgrid(np.arange(K.width_px), np.arange(K.height_px))
    dy = (v - K.cy_px) / K.fy_px  # downward component per unit depth
    depth = np.where(dy > 0, (0.6 - 0.45) / np.maximum(dy, 1e-9), 0.0).astype(np.float32)
    depth[depth > 6.0] = 0.0
    above = extract_band_scan(depth, K, T, VerticalBand(0.5, 0.8), stride_px=1)
    assert not above.is_hit.any()
    # Rays descend through the band: free space ends where they leave it (z = 0.5).
    reach = np.linalg.norm(above.far_xy_m[above.valid], axis=1)
    assert reach.max() <= 6.0 and reach.min() > 0.0
    inside = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8), stride_px=1)
    assert inside.is_hit.sum() > 0.9 * inside.n_rays


def test_sensor_above_band_frees_only_where_rays_cross_it() -> None:
    T = camera_pose(0.0, 0.0, 1.5, pitch_rad=math.radians(30))
    depth = wall_depth(3.0, T, wall_x_m=3.0)
    scan = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8), stride_px=1)
    hit = scan.is_hit & scan.valid
    assert hit.any()
    assert np.allclose(scan.hits_xy_m[:, 0], 3.0, atol=1e-3)
    # Free space starts where the descending rays enter the band, not at the sensor.
    assert np.all(scan.near_xy_m[scan.valid, 0] > 0.5)


def test_invalid_depth_says_nothing() -> None:
    T = camera_pose(0.0, 0.0, 0.6)
    depth = np.zeros((K.height_px, K.width_px), np.float32)
    depth[:, :10] = np.nan
    scan = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8))
    assert not scan.valid.any() and not scan.is_hit.any()
    far = np.full((K.height_px, K.width_px), 9.0, np.float32)  # beyond max range: invalid
    assert not extract_band_scan(far, K, T, VerticalBand(0.4, 0.8), max_depth_m=6.0).valid.any()


def test_a_single_flying_pixel_is_not_an_obstacle() -> None:
    T = camera_pose(0.0, 0.0, 0.6)
    depth = np.full((K.height_px, K.width_px), 4.0, np.float32)
    depth[60, 50] = 1.0  # one stray pixel in the band
    scan = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8), stride_px=1, min_hit_points=2)
    assert np.allclose(scan.hits_xy_m[:, 0], 4.0, atol=1e-4)
    single = extract_band_scan(depth, K, T, VerticalBand(0.4, 0.8), stride_px=1, min_hit_points=1)
    assert single.hits_xy_m[:, 0].min() == pytest.approx(1.0, abs=1e-3)


def test_a_thin_edge_between_dropouts_is_kept_by_the_strides() -> None:
    # A table top 2 m ahead, one pixel row tall (row 51, z = 0.69 m, in the band), in front of
    # a wall at 4 m; the sensor dropped the pixels above and below it (a depth edge). The
    # strides sample rows 50 and 52 only: without looking at the skipped pixels the top is
    # lost and the rays pass under it to the wall, clearing its footprint.
    T = camera_pose(1.0, 0.0, 0.6)
    depth = np.full((K.height_px, K.width_px), 4.0, np.float32)
    depth[50, :] = 0.0
    depth[51, :] = 2.0
    depth[52, :] = 0.0
    band = VerticalBand(0.4, 0.8)
    scan = extract_band_scan(depth, K, T, band, stride_px=2, column_stride_px=4)
    assert scan.is_hit.all()
    assert np.allclose(scan.hits_xy_m[:, 0], 3.0, atol=0.02)
    assert np.all(scan.far_xy_m[:, 0] <= 3.0 + 1e-6)
    plain = extract_band_scan(depth, K, T, band, stride_px=2, column_stride_px=4, recover_px=False)
    assert np.allclose(plain.hits_xy_m[:, 0], 5.0, atol=0.02)


def test_noisy_wall_hits_are_not_biased_towards_the_sensor() -> None:
    rng = np.random.default_rng(3)
    T = camera_pose(0.0, 0.0, 0.6)
    depth = (4.0 + rng.normal(0.0, 0.05, (K.height_px, K.width_px))).astype(np.float32)
    scan = extract_band_scan(depth, K, T, VerticalBand(0.3, 0.9), stride_px=1)
    assert float(np.median(scan.hits_xy_m[:, 0])) == pytest.approx(4.0, abs=0.02)
    assert np.all(scan.far_xy_m[:, 0] <= scan.hits_xy_m[:, 0] + 1e-6)


def test_bad_input_is_named() -> None:
    T = camera_pose(0.0, 0.0, 0.6)
    with pytest.raises(FrameError, match="intrinsics"):
        extract_band_scan(np.ones((10, 10), np.float32), K, T, VerticalBand(0.4, 0.8))
    with pytest.raises(FrameError, match="T_map_camera"):
        extract_band_scan(np.ones((120, 160), np.float32), K, np.eye(3), VerticalBand(0.4, 0.8))


def test_recentred_hit_sits_on_a_noisy_wall_where_the_nearest_cluster_falls_short() -> None:
    # A wall at 4 m with D455-like noise (sigma = 0.005 * z**2 = 8 cm): the nearest cluster's
    # mean is pulled towards the sensor, the re-centred mean is not.
    T = camera_pose(0.0, 0.0, 0.6)
    wall_m = 4.0
    rng = np.random.default_rng(3)
    depth = (wall_m + rng.normal(0.0, 0.005 * wall_m**2, (K.height_px, K.width_px))).astype(np.float32)
    band = VerticalBand(0.2, 1.0)
    nearest = extract_band_scan(depth, K, T, band, stride_px=1)
    centred = extract_band_scan(depth, K, T, band, stride_px=1, recentre_hit=True)
    # Per column, the wall's horizontal range along the ray is depth * |(x, 1)|.
    xn = (np.arange(K.width_px) - K.cx_px) / K.fx_px
    truth_m = wall_m * np.hypot(xn, 1.0)
    bias_nearest = np.mean(np.hypot(*nearest.hits_xy_m.T) - truth_m)
    bias_centred = np.mean(np.hypot(*centred.hits_xy_m.T) - truth_m)
    assert bias_nearest < -0.02
    assert abs(bias_centred) < 0.01
    assert np.array_equal(nearest.is_hit, centred.is_hit)
