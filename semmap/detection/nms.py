"""Class-aware non-maximum suppression.

Boxes of different classes never suppress each other (a chair under a desk survives the
desk's box). OpenCV's batched NMS does the work in C++; this module adapts its (x, y, w, h)
interface and top-k limits.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray


def nms_class_aware(
    xyxy_px: NDArray[np.float32],
    scores: NDArray[np.float32],
    class_ids: NDArray[np.int64],
    iou_threshold: float,
    max_detections: int,
    max_candidates: int = 3000,
) -> NDArray[np.int64]:
    """Indices of the boxes kept, best score first.

    ``xyxy_px``: (K, 4) boxes; ``scores``: (K,); ``class_ids``: (K,) any integer labels. A box
    is suppressed by a higher-scoring box of the same label whose IoU with it exceeds
    ``iou_threshold``. At most ``max_candidates`` top-scoring boxes are considered and at most
    ``max_detections`` returned.
    """
    n = int(scores.shape[0])
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.arange(n)
    if n > max_candidates:
        order = np.argpartition(-scores, max_candidates)[:max_candidates]
    boxes = xyxy_px[order].astype(np.float64)
    boxes[:, 2:4] -= boxes[:, 0:2]  # xyxy -> xywh in place
    # OpenCV's stubs claim lists; the binding takes arrays directly.
    nms: Any = cv2.dnn.NMSBoxesBatched
    keep = nms(
        boxes, scores[order].astype(np.float32), class_ids[order].astype(np.int32),
        0.0, float(iou_threshold),
    )
    kept = order[np.asarray(keep, dtype=np.int64).reshape(-1)]
    # OpenCV returns per-class groups; callers want a global best-first list.
    kept = kept[np.argsort(-scores[kept], kind="stable")]
    return kept[:max_detections]
