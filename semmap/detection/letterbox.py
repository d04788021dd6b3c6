"""Letterbox resize: fit an image into the network input without distorting it.

The two detector families we support were trained with different conventions, and a detector
fed the wrong one loses accuracy silently, so the style is explicit:

* ``yolov8`` (Ultralytics): RGB, values scaled to [0, 1], grey padding 114 split evenly on
  both sides (the image is centred), resize with bilinear interpolation.
* ``yolox`` (Megvii): BGR, raw 0..255 values, padding 114 on the right and bottom only (the
  image sits in the top-left corner).

:class:`LetterboxTransform` records scale and offsets so boxes can be mapped back to
original-image pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from semmap.errors import FrameError

LetterboxStyle = Literal["yolov8", "yolox"]

#: The grey both reference implementations pad with.
PAD_VALUE = 114


@dataclass(frozen=True)
class LetterboxTransform:
    """Maps network-input pixels back to original-image pixels.

    ``u_orig = (u_in - pad_left_px) / scale``; same for v with ``pad_top_px``.
    """

    scale: float
    pad_left_px: float
    pad_top_px: float
    orig_width_px: int
    orig_height_px: int

    def boxes_to_original(self, xyxy_in: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N, 4) boxes in network-input pixels -> (N, 4) original pixels, clipped to the image."""
        out = np.empty_like(xyxy_in)
        out[:, [0, 2]] = (xyxy_in[:, [0, 2]] - self.pad_left_px) / self.scale
        out[:, [1, 3]] = (xyxy_in[:, [1, 3]] - self.pad_top_px) / self.scale
        out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0.0, self.orig_width_px)
        out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0.0, self.orig_height_px)
        return out


def letterbox(
    image_rgb: NDArray[np.uint8],
    input_hw_px: tuple[int, int],
    style: LetterboxStyle,
) -> tuple[NDArray[np.float32], LetterboxTransform]:
    """Resize and pad an RGB image into a ``(1, 3, H_in, W_in)`` float32 network tensor.

    ``image_rgb``: (H, W, 3) uint8 RGB. ``input_hw_px``: network input (height, width).
    Returns the NCHW tensor and the transform back to original pixels. Raises
    :class:`FrameError` if the image is not (H, W, 3) uint8.
    """
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
        raise FrameError(
            f"detector input must be (H, W, 3) uint8 RGB (got shape {image_rgb.shape}, "
            f"dtype {image_rgb.dtype})"
        )
    h0, w0 = image_rgb.shape[:2]
    if h0 == 0 or w0 == 0:
        raise FrameError(f"detector input image is empty (shape {image_rgb.shape})")
    h_in, w_in = input_hw_px
    scale = min(h_in / h0, w_in / w0)
    if style == "yolov8":
        # Ultralytics LetterBox: new size rounded, padding split with its -0.1/+0.1 rounding.
        w_new, h_new = int(round(w0 * scale)), int(round(h0 * scale))
        dw, dh = (w_in - w_new) / 2.0, (h_in - h_new) / 2.0
        left, right = int(round(dw - 0.1)), int(round(dw + 0.1))
        top, bottom = int(round(dh - 0.1)), int(round(dh + 0.1))
        img: NDArray[Any] = image_rgb
    else:
        # YOLOX preproc: truncated size, image in the top-left corner, BGR.
        w_new, h_new = int(w0 * scale), int(h0 * scale)
        left, top = 0, 0
        right, bottom = w_in - w_new, h_in - h_new
        img = image_rgb
    if (w_new, h_new) != (w0, h0):
        img = cv2.resize(img, (w_new, h_new), interpolation=cv2.INTER_LINEAR)
    if top or bottom or left or right:
        img = cv2.copyMakeBorder(
            np.ascontiguousarray(img), top, bottom, left, right, cv2.BORDER_CONSTANT,
            value=(PAD_VALUE, PAD_VALUE, PAD_VALUE),
        )
    # HWC uint8 -> 1CHW float32 in one pass; YOLOX's BGR order is a free channel flip here.
    chw = img.transpose(2, 0, 1)
    if style == "yolox":
        chw = chw[::-1]
    tensor = np.empty((1, 3, h_in, w_in), dtype=np.float32)
    if style == "yolov8":
        np.multiply(chw, np.float32(1.0 / 255.0), out=tensor[0], dtype=np.float32)
    else:
        np.copyto(tensor[0], chw, casting="unsafe")
    # Ultralytics reports its scale from the rounded new size; the residual is < 0.5 px.
    return tensor, LetterboxTransform(float(scale), float(left), float(top), w0, h0)
