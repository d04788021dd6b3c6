"""The kernel warm-up runs every compiled step of the per-frame update once."""

from __future__ import annotations

from semmap import clustering, pointcloud, polygons, ransac, scan, shape_prior, walls
from semmap.kernels import warm_up


def test_warm_up_compiles_every_kernel() -> None:
    assert warm_up() >= 0.0
    for kernel in (pointcloud._window_table, clustering._linkage_labels, ransac._best_hypothesis,
                   walls._fit_wall, scan._scan_columns, shape_prior._solid_cells,
                   polygons._clip_convex):
        assert kernel.signatures, f"{kernel.__name__} was not compiled by warm_up"
