"""Association costs and assignment shared by BoT-SORT and the SORT baseline."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

#: Cost that no threshold accepts (used to forbid pairs, e.g. of different classes).
FORBIDDEN = 1e6


def iou_matrix(a_xyxy: NDArray[np.float64], b_xyxy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, M) intersection over union of (N, 4) and (M, 4) ``xyxy`` boxes (0 for empty boxes)."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros((a.shape[0], b.shape[0]))
    iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0.0, None) * np.clip(ih, 0.0, None)
    area_a = np.clip(a[:, 2] - a[:, 0], 0.0, None) * np.clip(a[:, 3] - a[:, 1], 0.0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0.0, None) * np.clip(b[:, 3] - b[:, 1], 0.0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0.0)


def fuse_score(cost: NDArray[np.float64], det_scores: NDArray[np.float64]) -> NDArray[np.float64]:
    """BoT-SORT's ``fuse_score``: ``1 - (1 - cost) * score`` per detection column."""
    if cost.size == 0:
        return cost
    return 1.0 - (1.0 - cost) * np.asarray(det_scores, dtype=np.float64)[None, :]


def linear_assignment(
    cost: NDArray[np.float64], thresh: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Minimum-cost matching (Hungarian, scipy) keeping only pairs with cost <= ``thresh``.

    ``cost``: (N, M). Returns matches (K, 2) of (row, col), unmatched rows, unmatched cols.
    Pairs above the threshold are made unattractive before solving, so an over-threshold pair
    never displaces a valid one.
    """
    n, m = cost.shape
    if n == 0 or m == 0:
        return np.zeros((0, 2), np.int64), np.arange(n), np.arange(m)
    c = np.where(cost > thresh, FORBIDDEN, cost)
    rows, cols = linear_sum_assignment(c)
    ok = c[rows, cols] <= thresh
    matches = np.stack([rows[ok], cols[ok]], axis=1).astype(np.int64)
    free_rows = np.ones(n, bool)
    free_rows[matches[:, 0]] = False
    free_cols = np.ones(m, bool)
    free_cols[matches[:, 1]] = False
    return matches, np.flatnonzero(free_rows), np.flatnonzero(free_cols)
