"""Decoding of raw detector outputs into candidate boxes (before NMS).

Two head layouts are understood, both for a single image (batch 1):

* ``yolov8``: ``(1, 4 + C, N)`` as written by the Ultralytics ONNX exporter. Rows 0..3 are
  box centre x, centre y, width, height in network-input pixels (DFL and strides already
  applied inside the graph); rows 4.. are per-class scores after sigmoid. No objectness.
* ``yolox``: ``(1, N, 5 + C)`` as written by YOLOX's ``tools/export_onnx.py``. Columns are
  box (4), objectness, per-class scores; objectness and class scores are already sigmoid-ed.
  The score of a class is ``objectness * class score``. By default that exporter leaves the
  box *undecoded* (``decode_in_inference`` off): ``x, y`` are offsets in grid cells and
  ``w, h`` log-sizes, decoded here as ``(xy + grid) * stride`` and ``exp(wh) * stride`` over
  the strides 8, 16, 32 in that order. Models exported with ``--decode_in_inference`` carry
  centre/size in input pixels already; pass ``predecoded=True`` for those.

Both give the same number of anchors ``N = sum((H/s) * (W/s))`` over the strides, which is how
:func:`recognise_head` tells the layouts apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from semmap.errors import PerceptionError

HeadKind = Literal["yolov8", "yolox"]

#: Feature-map strides of YOLOv8 and YOLOX (P3, P4, P5).
STRIDES_PX: tuple[int, ...] = (8, 16, 32)


@dataclass(frozen=True)
class Candidates:
    """Boxes above the score floor, in network-input pixels.

    ``xyxy_in_px``: (K, 4) float32; ``scores``: (K,) float32; ``class_ids``: (K,) int64 model
    class indices.
    """

    xyxy_in_px: NDArray[np.float32]
    scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def anchor_count(input_hw_px: tuple[int, int], strides: tuple[int, ...] = STRIDES_PX) -> int:
    """Number of anchor points of a stride-8/16/32 head for an (H, W) input."""
    h, w = input_hw_px
    return sum((h // s) * (w // s) for s in strides)


def recognise_head(
    output_shape: tuple[int, ...], input_hw_px: tuple[int, int], num_classes: int | None
) -> tuple[HeadKind, int]:
    """Which head wrote an output of ``output_shape``, and how many classes it has.

    Uses the anchor count of the input size first (unambiguous for stride-8/16/32 heads),
    then the class count if known. Raises :class:`PerceptionError` naming the shape and what
    was expected when neither layout fits.
    """
    if len(output_shape) != 3 or output_shape[0] != 1:
        raise PerceptionError(
            f"detector output has shape {list(output_shape)}; expected [1, 4+C, N] (YOLOv8) "
            f"or [1, N, 5+C] (YOLOX)"
        )
    _, a, b = output_shape
    n = anchor_count(input_hw_px)
    if b == n and a > 4 and (num_classes is None or a == 4 + num_classes):
        return "yolov8", a - 4
    if a == n and b > 5 and (num_classes is None or b == 5 + num_classes):
        return "yolox", b - 5
    if num_classes is not None:
        if a == 4 + num_classes and b > a:
            return "yolov8", num_classes
        if b == 5 + num_classes and a > b:
            return "yolox", num_classes
    raise PerceptionError(
        f"detector output shape {list(output_shape)} matches neither head for a "
        f"{input_hw_px[1]}x{input_hw_px[0]} input: YOLOv8 would be [1, 4+C, {n}], YOLOX "
        f"[1, {n}, 5+C]"
        + (f" with C = {num_classes} classes" if num_classes is not None else "")
    )


def check_head(
    head: HeadKind, output_shape: tuple[int, ...], num_classes: int | None
) -> int:
    """Validate ``output_shape`` against an explicitly configured head; returns the class count."""
    if len(output_shape) != 3 or output_shape[0] != 1:
        raise PerceptionError(f"detector output has shape {list(output_shape)}; expected 3 dims, batch 1")
    channels = output_shape[1] if head == "yolov8" else output_shape[2]
    extra = 4 if head == "yolov8" else 5
    c = channels - extra
    if c < 1 or (num_classes is not None and c != num_classes):
        want = f"{extra}+{num_classes}" if num_classes is not None else f"{extra}+C"
        axis = "[1, 4+C, N]" if head == "yolov8" else "[1, N, 5+C]"
        raise PerceptionError(
            f"detector.head is {head!r} ({axis}) but the model output is {list(output_shape)}: "
            f"expected {want} channels"
        )
    return c


def _select(
    boxes_cxcywh: NDArray[np.float32],
    class_scores: NDArray[np.float32],
    score_floor: float,
    class_mask: NDArray[np.bool_] | None,
) -> Candidates:
    """Best class per anchor, keep those above ``score_floor``, convert to xyxy.

    ``boxes_cxcywh``: (N, 4); ``class_scores``: (N, C); ``class_mask``: (C,) classes that may
    be reported (others are ignored before the argmax so they cannot shadow a wanted class).
    """
    if class_mask is not None:
        wanted = np.flatnonzero(class_mask)
        class_scores = class_scores[:, wanted]
    else:
        wanted = np.arange(class_scores.shape[1])
    if class_scores.shape[1] == 0:
        empty = np.zeros((0, 4), np.float32)
        return Candidates(empty, np.zeros(0, np.float32), np.zeros(0, np.int64))
    best = class_scores.argmax(axis=1)
    scores = np.take_along_axis(class_scores, best[:, None], axis=1)[:, 0]
    keep = np.flatnonzero(scores >= score_floor)
    b = boxes_cxcywh[keep]
    xyxy = np.empty((keep.size, 4), np.float32)
    xyxy[:, 0:2] = b[:, 0:2] - b[:, 2:4] * 0.5
    xyxy[:, 2:4] = b[:, 0:2] + b[:, 2:4] * 0.5
    return Candidates(xyxy, scores[keep].astype(np.float32), wanted[best[keep]].astype(np.int64))


def decode_yolov8(
    output: NDArray[np.float32],
    score_floor: float,
    class_mask: NDArray[np.bool_] | None = None,
) -> Candidates:
    """Decode a ``(1, 4 + C, N)`` YOLOv8 output; boxes in network-input pixels."""
    pred = output[0]  # (4 + C, N)
    return _select(pred[:4].T, pred[4:].T, score_floor, class_mask)


def _yolox_grid(input_hw_px: tuple[int, int], strides: tuple[int, ...]) -> tuple[
    NDArray[np.float32], NDArray[np.float32]
]:
    """Grid cell origins (N, 2) and per-anchor strides (N, 1) in YOLOX's anchor order."""
    h, w = input_hw_px
    grids, strd = [], []
    for s in strides:
        hs, ws = h // s, w // s
        yv, xv = np.meshgrid(np.arange(hs), np.arange(ws), indexing="ij")
        grids.append(np.stack((xv, yv), axis=2).reshape(-1, 2))
        strd.append(np.full((hs * ws, 1), s))
    return (
        np.concatenate(grids).astype(np.float32),
        np.concatenate(strd).astype(np.float32),
    )


class YoloxDecoder:
    """Decodes ``(1, N, 5 + C)`` YOLOX outputs; caches the anchor grid for one input size."""

    def __init__(
        self,
        input_hw_px: tuple[int, int],
        predecoded: bool = False,
        strides: tuple[int, ...] = STRIDES_PX,
    ) -> None:
        self.input_hw_px = input_hw_px
        self.predecoded = predecoded
        self._grid, self._stride = _yolox_grid(input_hw_px, strides)

    def __call__(
        self,
        output: NDArray[np.float32],
        score_floor: float,
        class_mask: NDArray[np.bool_] | None = None,
    ) -> Candidates:
        """Candidates with score = objectness x class score, boxes in network-input pixels."""
        pred = output[0]  # (N, 5 + C)
        if not self.predecoded and pred.shape[0] != self._grid.shape[0]:
            raise PerceptionError(
                f"YOLOX output has {pred.shape[0]} anchors; a {self.input_hw_px[1]}x"
                f"{self.input_hw_px[0]} input with strides 8/16/32 has {self._grid.shape[0]}"
            )
        obj = pred[:, 4]
        # Anchors whose objectness alone is below the floor can never pass: skip them early.
        live = np.flatnonzero(obj >= score_floor)
        p = pred[live]
        if self.predecoded:
            boxes = p[:, :4]
        else:
            g, s = self._grid[live], self._stride[live]
            boxes = np.empty((live.size, 4), np.float32)
            boxes[:, 0:2] = (p[:, 0:2] + g) * s
            boxes[:, 2:4] = np.exp(p[:, 2:4]) * s
        cls = p[:, 5:] * p[:, 4:5]
        return _select(boxes, cls, score_floor, class_mask)
