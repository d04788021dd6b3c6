"""Back-projection: the compiled window table against the numpy back-projection it replaces."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.frames import make_transform, rot_x
from semmap.pointcloud import backproject, window_points_map
from semmap.types import CameraIntrinsics

K = CameraIntrinsics(200.0, 210.0, 160.0, 120.0, 320, 240)


def _depth(rng: np.random.Generator, dtype: type) -> np.ndarray:
    d = rng.uniform(0.2, 7.0, (240, 320)).astype(dtype)
    d[rng.uniform(size=d.shape) < 0.1] = 0.0
    d[rng.uniform(size=d.shape) < 0.05] = np.nan
    d[rng.uniform(size=d.shape) < 0.02] = np.inf
    return d


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("depth_range", [(0.3, 6.0), (0.0, math.inf)])
def test_window_table_matches_backprojection_transform_and_floor_cut(dtype: type, depth_range: tuple[float, float]) -> None:
    rng = np.random.default_rng(3)
    d = _depth(rng, dtype)
    T = make_transform(rot_x(math.radians(-100.0)), np.array([0.4, -0.2, 1.1]))
    normal, offset = np.array([0.02, -0.01, 1.0]) / np.linalg.norm([0.02, -0.01, 1.0]), 0.03
    for window, stride in (((20, 10, 300, 230), 1), ((0, 0, 320, 240), 3), ((100, 50, 140, 90), 2)):
        tab, n_valid = window_points_map(d, K, *depth_range, window, stride, T, normal, offset, 0.04, 0.006)
        pts, uv = (a.T for a in backproject(d, K, *depth_range, window, stride))
        xyz = T[:3, :3] @ pts + T[:3, 3][:, None]
        h = normal @ xyz + offset
        rng_m = pts[2].astype(np.float64)
        clear = rng_m**2 * 0.006 + 0.04
        keep = h > clear
        assert n_valid == pts.shape[1]
        assert tab.shape == (8, int(keep.sum()))
        np.testing.assert_allclose(tab[:3], xyz[:, keep], rtol=0, atol=1e-12)
        np.testing.assert_allclose(tab[3], h[keep], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(tab[4], rng_m[keep])
        np.testing.assert_allclose(tab[5], clear[keep], rtol=0, atol=1e-15)
        np.testing.assert_array_equal(tab[6:], uv[:, keep])


def test_an_empty_window_gives_no_points() -> None:
    d = _depth(np.random.default_rng(4), np.float32)
    assert backproject(d, K, 0.3, 6.0, (50, 50, 50, 90), 1)[0].shape == (0, 3)
    assert window_points_map(d, K, 0.3, 6.0, (50, 50, 50, 90), 1, np.eye(4), np.array([0, 0, 1.0]), 0.0, 0.0, 0.0)[1] == 0


def test_window_table_skips_the_hole() -> None:
    d = _depth(np.random.default_rng(5), np.float32)
    up, off = np.array([0.0, 0.0, 1.0]), 0.0
    full, n_full = window_points_map(d, K, 0.3, 6.0, (10, 10, 200, 150), 4, np.eye(4), up, off, -1e9, 0.0)
    ring, n_ring = window_points_map(d, K, 0.3, 6.0, (10, 10, 200, 150), 4, np.eye(4), up, off, -1e9, 0.0,
                                     hole_px=(50, 42, 130, 90))
    u, v = full[6], full[7]
    outside = ~((u >= 50) & (u < 130) & (v >= 42) & (v < 90))
    np.testing.assert_array_equal(ring, full[:, outside])
    assert n_ring == int(outside.sum()) < n_full
