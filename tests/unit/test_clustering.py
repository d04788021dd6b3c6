"""Voxel downsampling and Euclidean clustering (exact single linkage at the distance)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

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
    labels = euclidean_clusters(np.concatenate([small, big]), 0.1)
    assert set(labels[:50]) == {1}
    assert set(labels[50:]) == {0}
    idx = largest_cluster(np.concatenate([small, big]), 0.1)
    assert len(idx) == 300 and idx.min() == 50


def test_small_clusters_are_noise() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [5.0, 5.0, 5.0]])
    labels = euclidean_clusters(pts, 0.05, min_points=2)
    assert labels.tolist() == [0, 0, -1]


def test_empty_input() -> None:
    assert len(euclidean_clusters(np.zeros((0, 3)), 0.1)) == 0
    c, inv = voxel_downsample(np.zeros((0, 3)), 0.1)
    assert c.shape == (0, 3) and len(inv) == 0


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two labellings (N,) group the points identically (label values aside)."""
    return bool(np.array_equal(a[:, None] == a[None, :], b[:, None] == b[None, :]))


def _brute_force_linkage(pts: np.ndarray, d: float) -> np.ndarray:
    """Single-linkage components by all pairwise squared distances (the definition)."""
    diff = pts[:, None, :] - pts[None, :, :]
    linked = (diff[..., 0] ** 2 + diff[..., 1] ** 2 + diff[..., 2] ** 2) <= d * d
    return connected_components(csr_matrix(linked), directed=False)[1]


@settings(max_examples=60, deadline=None)
@given(
    pts=arrays(np.float64, st.tuples(st.integers(2, 80), st.just(3)),
               elements=st.floats(-1.0, 1.0, allow_nan=False)),
    d=st.floats(0.02, 0.5),
)
def test_clusters_are_exact_single_linkage(pts: np.ndarray, d: float) -> None:
    labels = euclidean_clusters(pts, d)
    assert _same_partition(labels, _brute_force_linkage(pts, d))
    # Points of different clusters are more than d apart, in true distance.
    apart = labels[:, None] != labels[None, :]
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    assert np.all(dist[apart] > d * (1 - 1e-9))


def test_groups_farther_apart_than_the_distance_stay_apart_even_in_touching_cells() -> None:
    # Two points 1.5 d apart along a diagonal sit in neighbouring cells of side d (cell
    # connectivity would join them, and so the object with the wall behind it).
    d = 0.05
    a = np.array([[0.049, 0.049, 0.049]])
    b = a + 1.5 * d / np.sqrt(3.0)
    labels = euclidean_clusters(np.concatenate([a, b]), d)
    assert labels.tolist() in ([0, 1], [1, 0])
    # A surface and a parallel one 0.06 m behind it, distance 0.05: two clusters.
    g = np.stack(np.meshgrid(np.arange(0, 0.5, 0.03), np.arange(0, 0.5, 0.03)), -1).reshape(-1, 2)
    front = np.column_stack([g, np.zeros(len(g))])
    back = np.column_stack([g[:-10], np.full(len(g) - 10, 0.06)])
    labels = euclidean_clusters(np.concatenate([front, back]), d)
    assert set(labels[: len(front)]) == {0} and set(labels[len(front):]) == {1}


def test_chains_of_links_within_the_distance_join() -> None:
    d = 0.05
    # A helix sampled every 0.049 m: every link within d, ends far apart - one cluster.
    s = np.arange(0.0, 3.0, 0.049)
    r, pitch = 0.3, 0.2
    t = s / np.hypot(r, pitch / (2 * np.pi))
    chain = np.column_stack([r * np.cos(t), r * np.sin(t), pitch * t / (2 * np.pi)])
    assert np.all(np.linalg.norm(np.diff(chain, axis=0), axis=1) <= d)
    assert np.all(euclidean_clusters(chain, d) == 0)
    # Cut one link (move the second half 0.02 m further along the last link): two clusters.
    cut = chain.copy()
    step = chain[31] - chain[30]
    cut[31:] += 0.02 * step / np.linalg.norm(step)
    labels = euclidean_clusters(cut, d)
    assert len(set(labels[:31])) == 1 and len(set(labels[31:])) == 1 and labels[0] != labels[-1]
    # A link of exactly d joins (at most d, as DBSCAN's eps).
    assert euclidean_clusters(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.25]]), 0.25).tolist() == [0, 0]


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


def test_sparse_cells_give_the_dense_labels(monkeypatch) -> None:
    rng = np.random.default_rng(8)
    for _ in range(20):
        pts = rng.uniform(0.0, rng.choice([0.3, 3.0]), (int(rng.integers(2, 300)), 3))
        d = float(rng.uniform(0.03, 0.3))
        dense = euclidean_clusters(pts, d)
        monkeypatch.setattr(clustering, "_DENSE_CELLS_PER_POINT", -(10**9))
        sparse = euclidean_clusters(pts, d)
        monkeypatch.undo()
        assert np.array_equal(dense, sparse)
        assert _same_partition(dense, _brute_force_linkage(pts, d))
