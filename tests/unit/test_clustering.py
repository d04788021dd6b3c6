"""Voxel downsampling and voxel-connectivity Euclidean clustering."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from semmap import clustering
from semmap.clustering import euclidean_clusters, largest_cluster, voxel_downsample


def test_voxel_downsample_means_points_per_voxel() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.51, 0.0, 0.0]])
    cent, inv = voxel_downsample(pts, 0.1)
    assert len(cent) == 2
    assert inv[0] == inv[1] != inv[2]
    np.testing.assert_allclose(cent[inv[0]], [0.015, 0.015, 0.015])
    np.testing.assert_allclose(cent[inv[2]], [0.51, 0.0, 0.0])


def test_two_blobs_are_two_clusters_ordered_by_size() -> None:
    rng = np.random.default_rng(0)
    big = rng.uniform(0.0, 0.3, (300, 3))
    small = rng.uniform(0.0, 0.1, (50, 3)) + [2.0, 0.0, 0.0]
    labels = euclidean_clusters(np.concatenate([small, big]), 0.05)
    assert set(labels[:50]) == {1}
    assert set(labels[50:]) == {0}
    idx = largest_cluster(np.concatenate([small, big]), 0.05)
    assert len(idx) == 300 and idx.min() == 50


def test_small_clusters_are_noise() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [5.0, 5.0, 5.0]])
    labels = euclidean_clusters(pts, 0.05, min_points=2)
    assert labels.tolist() == [0, 0, -1]


def test_empty_input() -> None:
    assert len(euclidean_clusters(np.zeros((0, 3)), 0.1)) == 0
    c, inv = voxel_downsample(np.zeros((0, 3)), 0.1)
    assert c.shape == (0, 3) and len(inv) == 0


@settings(max_examples=40, deadline=None)
@given(
    pts=arrays(np.float64, st.tuples(st.integers(2, 60), st.just(3)),
               elements=st.floats(-1.0, 1.0, allow_nan=False)),
    d=st.floats(0.02, 0.5),
)
def test_close_points_share_a_cluster_and_clusters_are_apart(pts: np.ndarray, d: float) -> None:
    labels = euclidean_clusters(pts, d)
    diff = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    close = diff < d
    assert np.all((labels[:, None] == labels[None, :]) | ~close)
    # Points of different clusters are more than d apart along some axis.
    apart = labels[:, None] != labels[None, :]
    axis_gap = np.abs(pts[:, None, :] - pts[None, :, :]).max(axis=2)
    assert np.all(axis_gap[apart] > d * (1 - 1e-9))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 300), spread=st.sampled_from([0.05, 0.5, 50.0]), voxel=st.floats(0.01, 0.2),
    seed=st.integers(0, 1000),
)
def test_voxel_downsample_matches_a_per_voxel_mean(n: int, spread: float, voxel: float, seed: int) -> None:
    # Small spreads take the compact-key path, large ones the sorted-key path.
    pts = np.random.default_rng(seed).uniform(0.0, spread, (n, 3))
    cent, inv = voxel_downsample(pts, voxel)
    groups: dict[tuple[int, int, int], list[int]] = {}
    for i, key in enumerate(map(tuple, np.floor(pts / voxel).astype(int))):
        groups.setdefault(key, []).append(i)
    assert len(cent) == len(groups)
    for members in groups.values():
        assert len(set(inv[members])) == 1
        np.testing.assert_allclose(cent[inv[members[0]]], pts[members].mean(axis=0), atol=1e-12)


def test_dense_and_sparse_labelling_agree() -> None:
    rng = np.random.default_rng(7)
    blobs = np.concatenate([rng.normal(c, 0.03, (80, 3)) for c in ([0, 0, 0], [0.5, 0, 0], [0, 0.6, 0.2])])
    dense = euclidean_clusters(blobs, 0.05)
    # One far point makes the bounding grid huge (the axis compression keeps it small).
    far = euclidean_clusters(np.concatenate([blobs, [[500.0, 500.0, 500.0]]]), 0.05)
    assert np.array_equal(dense, far[:-1])


def test_sparse_fallback_gives_the_compiled_labels(monkeypatch) -> None:
    rng = np.random.default_rng(8)
    for _ in range(20):
        pts = rng.uniform(0.0, rng.choice([0.3, 3.0]), (int(rng.integers(2, 300)), 3))
        d = float(rng.uniform(0.03, 0.3))
        compiled = euclidean_clusters(pts, d)
        monkeypatch.setattr(clustering, "_DENSE_MAX_CELLS", 0)
        sparse = euclidean_clusters(pts, d)
        monkeypatch.undo()
        assert np.array_equal(compiled, sparse)
