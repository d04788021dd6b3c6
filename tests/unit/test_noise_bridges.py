"""A coffee table 0.3 m in front of a sofa, seen from afar through noisy depth, is not the sofa."""

from __future__ import annotations

import numpy as np

from semmap.clustering import euclidean_clusters
from semmap.config import ClassConfig, GeometryConfig
from semmap.geometry import observe_object
from semmap.noise_bridges import dense_parts
from semmap.types import Track
from tests.unit.test_geometry import FLOOR, K, box_of, camera_pose, render

SOFA = ClassConfig(name="sofa", hollow="none", margin_m=0.15, color_rgb=(1, 2, 3))
COFFEE_TABLE = ClassConfig(name="coffee_table", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3), shape="table")
# A sofa against the far wall, its front at x = 5.0: base to the seat (0.42 m), back to 0.85 m.
SOFA_BOXES = [((5.0, 0.1, 0.0), (5.9, 1.9, 0.42)), ((5.7, 0.1, 0.42), (5.9, 1.9, 0.85))]
# A coffee table 0.3 m in front of it: top 0.42-0.45 m on four legs, x 4.15-4.70.
TABLE_BOXES = [((4.15, 0.4, 0.42), (4.70, 1.6, 0.45))] + [
    ((x, y, 0.0), (x + 0.04, y + 0.04, 0.42)) for x in (4.17, 4.64) for y in (0.42, 1.54)]
# Seen from 3.5 m at the flight band, looking over the table at the sofa.
T_CAM = camera_pose(1.5, 1.0, 1.2, 0.0, 15.0)


def _noisy_depth(seed: int) -> np.ndarray:
    """The scene's depth with a D455's noise: sigma 0.005 z^2 along each ray (6 cm at 3.5 m)."""
    depth = render(SOFA_BOXES + TABLE_BOXES + [FLOOR], T_CAM)
    rng = np.random.default_rng(seed)
    return np.where(depth > 0, depth + rng.normal(0.0, 1.0, depth.shape) * 0.005 * depth**2, 0.0)


def test_noisy_views_of_a_sofa_do_not_take_the_coffee_table_in_front_of_it() -> None:
    clean = 0
    for seed in range(10):
        depth = _noisy_depth(seed)
        sofa = observe_object(depth, K, T_CAM, Track(1, box_of(SOFA_BOXES, T_CAM), 0.9, "sofa"), SOFA,
                              GeometryConfig(), depth_range_m=(0.3, 8.0))
        assert sofa is not None
        # The table spans x 4.15-4.70; the sofa's noisy front reaches a few centimetres nearer than 5.0.
        clean += int(np.mean(sofa.voxels_map_m[:, 0] < 4.75) < 0.01)
    # Single linkage through the noise in the gap joins them in every one of these views.
    assert clean >= 8


def test_a_gap_bridged_by_a_few_noisy_points_splits_and_a_sparse_surface_does_not() -> None:
    rng = np.random.default_rng(3)
    near = np.column_stack([rng.uniform(4.15, 4.7, 600), rng.uniform(0.4, 1.6, 600), rng.uniform(0.42, 0.45, 600)])
    far = np.column_stack([rng.uniform(5.0, 5.3, 900), rng.uniform(0.1, 1.9, 900), rng.uniform(0.0, 0.42, 900)])
    gap = np.column_stack([np.linspace(4.72, 4.98, 6), np.full(6, 1.0), np.full(6, 0.43)])  # noise in the gap
    pts = np.concatenate([near, far, gap])
    assert (euclidean_clusters(pts, 0.2) == 0).all()  # single linkage joins them
    parts = dense_parts(pts, 0.2)
    assert len(set(parts[:600])) == 1 and len(set(parts[600:1500])) == 1 and parts[0] != parts[600]
    # A top seen at a grazing angle: rows 0.12 m apart, each dense; it stays one part.
    rows = np.concatenate([np.column_stack([np.full(80, x), rng.uniform(0.0, 1.2, 80), np.full(80, 0.75)])
                           for x in np.arange(3.0, 4.2, 0.12)])
    assert (dense_parts(rows, 0.2) == 0).all()
