"""Plain SORT (Bewley et al., 2016): the baseline BoT-SORT is benchmarked against.

Faithful to the original ``sort.py``: a Kalman filter on ``[u, v, s, r, du, dv, ds]`` (centre,
area, aspect ratio; constant velocity, the aspect ratio constant) with SORT's hand-set noise,
``1 - IoU`` cost, Hungarian assignment with an IoU floor, no camera-motion compensation, no
low-score stage, no appearance. A track is reported once it has ``min_hits`` consecutive hits
(or during the first ``min_hits`` frames) and deleted after ``max_age`` frames without one.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from semmap.tracking.matching import iou_matrix, linear_assignment
from semmap.types import Detection, Track

_F = np.eye(7)
_F[0, 4] = _F[1, 5] = _F[2, 6] = 1.0
_H = np.eye(4, 7)
# SORT's noise: R[2:, 2:] *= 10; P[4:, 4:] *= 1000; P *= 10; Q[-1, -1] *= 0.01; Q[4:, 4:] *= 0.01.
_R = np.diag([1.0, 1.0, 10.0, 10.0])
_P0 = np.diag([10.0, 10.0, 10.0, 10.0, 1e4, 1e4, 1e4])
_Q = np.diag([1.0, 1.0, 1.0, 1.0, 0.01, 0.01, 1e-4])


def _to_z(xyxy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(4,) xyxy -> (4,) [u, v, area, aspect]."""
    w, h = xyxy[2] - xyxy[0], xyxy[3] - xyxy[1]
    return np.array([xyxy[0] + w / 2.0, xyxy[1] + h / 2.0, w * h, w / max(h, 1e-9)])


def _to_xyxy(x: NDArray[np.float64]) -> NDArray[np.float64]:
    s, r = max(x[2], 0.0), max(x[3], 1e-9)
    w = np.sqrt(s * r)
    h = s / max(w, 1e-9)
    return np.array([x[0] - w / 2.0, x[1] - h / 2.0, x[0] + w / 2.0, x[1] + h / 2.0])


class _KalmanBoxTracker:
    __slots__ = ("x", "P", "track_id", "class_name", "score", "time_since_update", "hits",
                 "hit_streak", "age")

    def __init__(self, det: Detection, track_id: int) -> None:
        self.x = np.zeros(7)
        self.x[:4] = _to_z(np.asarray(det.xyxy_px, dtype=np.float64))
        self.P = _P0.copy()
        self.track_id = track_id
        self.class_name = det.class_name
        self.score = det.score
        self.time_since_update = 0
        self.hits = 0
        self.hit_streak = 0
        self.age = 0

    def predict(self) -> NDArray[np.float64]:
        if self.x[6] + self.x[2] <= 0:
            self.x[6] = 0.0
        self.x = _F @ self.x
        self.P = _F @ self.P @ _F.T + _Q
        self.age += 1
        if self.time_since_update > 0:
            self.hit_streak = 0
        self.time_since_update += 1
        return _to_xyxy(self.x)

    def update(self, det: Detection) -> None:
        self.time_since_update = 0
        self.hits += 1
        self.hit_streak += 1
        self.score = det.score
        z = _to_z(np.asarray(det.xyxy_px, dtype=np.float64))
        S = _H @ self.P @ _H.T + _R
        K = np.linalg.solve(S, _H @ self.P).T
        self.x = self.x + K @ (z - _H @ self.x)
        self.P = (np.eye(7) - K @ _H) @ self.P


class SORT:
    """The SORT tracker. Feed every frame's detections in order."""

    def __init__(self, max_age: int = 1, min_hits: int = 3, iou_threshold: float = 0.3) -> None:
        """``max_age``: frames a track survives unmatched; ``min_hits``: hits before it is
        reported; ``iou_threshold``: minimum IoU of a match."""
        self.max_age = max_age
        self.min_hits = min_hits
        self.iou_threshold = iou_threshold
        self.frame_count = 0
        self._ids = itertools.count(1)
        self._trackers: list[_KalmanBoxTracker] = []

    def update(self, detections: Sequence[Detection]) -> list[Track]:
        """Advance one frame; returns the reported tracks (boxes from the filter state)."""
        self.frame_count += 1
        preds = [t.predict() for t in self._trackers]
        keep = [i for i, p in enumerate(preds) if np.all(np.isfinite(p))]
        self._trackers = [self._trackers[i] for i in keep]
        pred_boxes = np.array([preds[i] for i in keep]).reshape(-1, 4)
        det_boxes = np.array([d.xyxy_px for d in detections], dtype=np.float64).reshape(-1, 4)
        cost = 1.0 - iou_matrix(pred_boxes, det_boxes)
        matches, _, u_det = linear_assignment(cost, 1.0 - self.iou_threshold)
        for ti, di in matches:
            self._trackers[ti].update(detections[di])
        for di in u_det:
            self._trackers.append(_KalmanBoxTracker(detections[di], next(self._ids)))
        out: list[Track] = []
        alive = []
        for t in self._trackers:
            if t.time_since_update < 1 and (t.hit_streak >= self.min_hits or self.frame_count <= self.min_hits):
                u0, v0, u1, v1 = (float(v) for v in _to_xyxy(t.x))
                out.append(Track(t.track_id, (u0, v0, u1, v1), float(t.score), t.class_name, t.age))
            if t.time_since_update <= self.max_age:
                alive.append(t)
        self._trackers = alive
        return out
