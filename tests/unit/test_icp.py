"""Point-to-plane ICP (bench/_icp.py) on synthetic clouds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench._icp import estimate_normals, icp_point_to_plane, register_clouds, voxel_downsample
from semmap.errors import PerceptionError


def _room_corner_cloud(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """Points on three orthogonal planes and a box, in front of a camera at the origin."""
    k = n // 4
    floor = np.stack([rng.uniform(-1, 1, k), np.full(k, 0.8), rng.uniform(1, 3, k)], axis=1)
    wall = np.stack([rng.uniform(-1, 1, k), rng.uniform(-1, 0.8, k), np.full(k, 3.0)], axis=1)
    side = np.stack([np.full(k, -1.0), rng.uniform(-1, 0.8, k), rng.uniform(1, 3, k)], axis=1)
    box = np.stack([rng.uniform(0.2, 0.6, k), rng.uniform(0.3, 0.8, k), np.full(k, 2.0)], axis=1)
    return np.concatenate([floor, wall, side, box])


def test_icp_recovers_a_known_motion() -> None:
    rng = np.random.default_rng(0)
    target = _room_corner_cloud(rng)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [1.5, -2.0, 1.0], degrees=True).as_matrix()
    T[:3, 3] = [0.03, -0.02, 0.05]
    # Source: the same surfaces seen from the moved camera (resampled + noise).
    source_in_target = _room_corner_cloud(np.random.default_rng(1)) + rng.normal(0, 0.002, (3000, 3))
    source = (source_in_target - T[:3, 3]) @ T[:3, :3]  # inverse of T applied
    res = register_clouds(source, target, voxels_m=(0.04, 0.02))
    err = np.linalg.inv(T) @ res.T_target_source
    assert np.linalg.norm(err[:3, 3]) < 0.005
    assert np.degrees(Rotation.from_matrix(err[:3, :3]).magnitude()) < 0.2
    assert res.fitness > 0.3
    # Three planes and a box constrain all six directions.
    assert np.linalg.eigvalsh(res.information)[0] > 0.0


def test_normals_of_a_plane_face_the_sensor() -> None:
    rng = np.random.default_rng(2)
    pts = np.stack([rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500), np.full(500, 2.0)], axis=1)
    n, ok = estimate_normals(pts)
    assert ok.all()
    np.testing.assert_allclose(n[:, 2], -1.0, atol=1e-6)


def test_voxel_downsample_keeps_one_centroid_per_voxel() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.51, 0.0, 0.0]])
    out = voxel_downsample(pts, 0.1)
    assert len(out) == 2
    assert any(np.allclose(p, [0.02, 0.02, 0.02]) for p in out)


def test_icp_without_overlap_names_the_problem() -> None:
    a = np.random.default_rng(3).uniform(0, 1, (100, 3))
    with pytest.raises(PerceptionError, match="correspondence"):
        icp_point_to_plane(a, a + 10.0, max_correspondence_m=0.05)
    with pytest.raises(PerceptionError, match="at least 6"):
        icp_point_to_plane(a[:3], a)
