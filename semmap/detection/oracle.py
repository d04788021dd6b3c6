"""The simulator's "oracle" detector: boxes from the renderer's instance masks.

It lets everything downstream of the detector (tracking, geometry, mapping, planning) run
before a trained model exists, with a detector whose failure modes are controlled and seeded:

* a box is the bounding box of an object's visible pixels (half-open max, like detector
  boxes), jittered by Gaussian noise of ``box_noise_px`` per edge;
* objects with fewer than ``min_visible_px`` pixels are not seen;
* each seen object is missed with probability ``miss_rate``;
* with probability ``false_positive_rate`` per frame a spurious box of a random class appears;
* scores behave like a real detector's: 0.5-0.95 for well-visible objects, lower for small or
  image-border-truncated ones (so the tracker's low-score second stage is exercised).

Class names come from the caller's ``object_classes`` (object id -> class name, which the
simulated world knows) or, if not given, from the frame's ``"class"`` mask (class indices into
``class_names``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from semmap.config import DetectorConfig
from semmap.errors import FrameError
from semmap.types import Detection, Frame

#: Pixel count at which an object counts as fully visible for scoring, in units of
#: ``min_visible_px``.
_FULL_VISIBILITY_FACTOR = 12.0


class OracleDetector:
    """Boxes from ``Frame.masks["instance"]`` with seeded noise, misses and false positives."""

    def __init__(
        self,
        class_names: Sequence[str],
        *,
        object_classes: Mapping[int, str] | None = None,
        box_noise_px: float = 3.0,
        miss_rate: float = 0.05,
        false_positive_rate: float = 0.02,
        min_visible_px: int = 400,
        seed: int = 0,
    ) -> None:
        """``class_names``: our classes, in the order of the ``"class"`` mask's indices."""
        self.class_names = list(class_names)
        self.object_classes = dict(object_classes) if object_classes is not None else None
        self.box_noise_px = float(box_noise_px)
        self.miss_rate = float(miss_rate)
        self.false_positive_rate = float(false_positive_rate)
        self.min_visible_px = int(min_visible_px)
        self._rng = np.random.default_rng(seed)

    @classmethod
    def from_config(
        cls,
        cfg: DetectorConfig,
        class_names: Sequence[str],
        object_classes: Mapping[int, str] | None = None,
        seed: int = 0,
    ) -> OracleDetector:
        """Build from the ``oracle_*`` fields of :class:`DetectorConfig`."""
        return cls(
            class_names,
            object_classes=object_classes,
            box_noise_px=cfg.oracle_box_noise_px,
            miss_rate=cfg.oracle_miss_rate,
            false_positive_rate=cfg.oracle_false_positive_rate,
            min_visible_px=cfg.oracle_min_visible_px,
            seed=seed,
        )

    def _class_of(
        self, object_id: int, sl: tuple[slice, slice], inst: NDArray[np.int32], cls_mask: NDArray[np.generic] | None
    ) -> str | None:
        if self.object_classes is not None:
            return self.object_classes.get(object_id)
        if cls_mask is None:
            raise FrameError(
                "oracle detector: frame has no 'class' mask and no object_classes were given"
            )
        vals = cls_mask[sl][inst[sl] == object_id].astype(np.int64)
        vals = vals[(vals >= 0) & (vals < len(self.class_names))]
        if vals.size == 0:
            return None
        return self.class_names[int(np.bincount(vals).argmax())]

    def ground_truth_boxes(self, frame: Frame) -> dict[int, tuple[tuple[float, float, float, float], int]]:
        """Object id -> (exact visible-pixel box ``xyxy_px``, pixel count) for visible objects.

        Objects below ``min_visible_px`` are left out. Raises :class:`FrameError` if the frame
        has no ``"instance"`` mask of the image's size.
        """
        inst = frame.masks.get("instance")
        h, w = frame.rgb.shape[:2]
        if inst is None:
            raise FrameError("oracle detector needs frame.masks['instance'] (a simulated frame)")
        if inst.shape != (h, w):
            raise FrameError(f"frame.masks['instance'] has shape {inst.shape}, image is {(h, w)}")
        labels = np.asarray(inst, dtype=np.int32)
        if labels.max(initial=0) <= 0:
            return {}
        counts = np.bincount(labels[labels > 0].ravel())
        out: dict[int, tuple[tuple[float, float, float, float], int]] = {}
        for i, sl in enumerate(ndimage.find_objects(labels), start=1):
            if sl is None or counts[i] < self.min_visible_px:
                continue
            ys, xs = sl
            box = (float(xs.start), float(ys.start), float(xs.stop), float(ys.stop))
            out[i] = (box, int(counts[i]))
        return out

    def _score(self, box: tuple[float, float, float, float], pixels: int, w: int, h: int) -> float:
        """A detector-like confidence: high when large and whole, lower when small or cut off."""
        visibility = min(1.0, np.sqrt(pixels / (_FULL_VISIBILITY_FACTOR * self.min_visible_px)))
        u0, v0, u1, v1 = box
        truncated = u0 <= 0.0 or v0 <= 0.0 or u1 >= w or v1 >= h
        quality = visibility * (0.7 if truncated else 1.0)
        score = 0.35 + 0.6 * quality + self._rng.normal(0.0, 0.05)
        return float(np.clip(score, 0.05, 0.97))

    def detect_frame(self, frame: Frame) -> list[Detection]:
        """Detections for one simulated frame, boxes in image pixels, best score first."""
        h, w = frame.rgb.shape[:2]
        cls_mask = frame.masks.get("class")
        inst = np.asarray(frame.masks.get("instance"))
        dets: list[Detection] = []
        for obj_id, (box, pixels) in self.ground_truth_boxes(frame).items():
            if self._rng.random() < self.miss_rate:
                continue
            ys = slice(int(box[1]), int(box[3]))
            xs = slice(int(box[0]), int(box[2]))
            name = self._class_of(obj_id, (ys, xs), inst, cls_mask)
            if name is None:
                continue
            score = self._score(box, pixels, w, h)
            noisy = np.asarray(box) + self._rng.normal(0.0, self.box_noise_px, 4)
            u0, u1 = np.clip(np.sort(noisy[[0, 2]]), 0.0, w)
            v0, v1 = np.clip(np.sort(noisy[[1, 3]]), 0.0, h)
            if u1 - u0 < 2.0 or v1 - v0 < 2.0:
                continue
            dets.append(Detection((float(u0), float(v0), float(u1), float(v1)), score, name))
        if self.class_names and self._rng.random() < self.false_positive_rate:
            dets.append(self._false_positive(w, h))
        dets.sort(key=lambda d: -d.score)
        return dets

    def _false_positive(self, w: int, h: int) -> Detection:
        bw = self._rng.uniform(0.05, 0.3) * w
        bh = self._rng.uniform(0.05, 0.3) * h
        u0 = self._rng.uniform(0.0, w - bw)
        v0 = self._rng.uniform(0.0, h - bh)
        name = self.class_names[int(self._rng.integers(len(self.class_names)))]
        score = float(self._rng.uniform(0.2, 0.7))
        return Detection((u0, v0, u0 + bw, v0 + bh), score, name)
