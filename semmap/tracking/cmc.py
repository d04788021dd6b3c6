"""Camera-motion compensation: the global image motion between consecutive frames.

BoT-SORT's sparse optical flow variant (``GMC`` with ``sparseOptFlow``), with the objects
masked out as its feature-based variants do: corners are found on the background of the
previous frame (``cv2.goodFeaturesToTrack``, outside detection boxes and the image border),
followed into the current frame with pyramidal Lucas-Kanade
(``cv2.calcOpticalFlowPyrLK``), and a motion model is fitted robustly with RANSAC, so moving
or tracked objects do not drag the estimate. The work runs on a downscaled grey image; the
result is scaled back to full-resolution pixels.

Two motion models:

* ``affine``: BoT-SORT's 4-DoF similarity (rotation, uniform scale, translation;
  ``cv2.estimateAffinePartial2D``). Exact for a camera translating along its axis or rolling.
* ``homography`` (default): 8-DoF projective (``cv2.findHomography``). A camera *rotating*
  about its centre moves every pixel by a homography, whatever the depth, and a yawing drone
  is mostly that. With an 80 deg field of view, 4 deg of yaw per frame (60 deg/s at 15 Hz)
  shifts the image edges 1.7 times more than its centre and bends rows; a similarity cannot
  follow that, and its RANSAC fit then favours one image region and is wrong elsewhere.

The result is a (3, 3) matrix ``H`` mapping previous-frame pixels to current-frame pixels,
``p_curr ~ H @ [u, v, 1]`` (an affine has last row ``[0, 0, 1]``). When too few features
survive (a blank wall, the first frame, a cut) it is the identity, which is what the tracker
would assume without CMC.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from semmap.errors import FrameError

log = logging.getLogger(__name__)

IDENTITY = np.eye(3)

#: Fewer RANSAC inliers than this and the estimate is not trusted.
MIN_INLIERS = 8
#: A frame-to-frame homography whose local area change at the image centre is outside
#: [1 / MAX_AREA_CHANGE, MAX_AREA_CHANGE] is a bad fit, not camera motion.
MAX_AREA_CHANGE = 1.5

#: Fraction of the image (bounding box of the inliers) a homography's inliers must span.
MIN_HOMOGRAPHY_SPREAD = 0.2

MotionModel = Literal["homography", "affine"]


class SparseFlowCMC:
    """Frame-to-frame global motion from sparse optical flow on background features."""

    def __init__(
        self,
        downscale: int = 2,
        max_features: int = 200,
        min_distance_px: float = 6.0,
        quality_level: float = 0.01,
        border_frac: float = 0.02,
        ransac_reproj_px: float = 1.5,
        lk_window_px: int = 11,
        lk_levels: int = 3,
        model: MotionModel = "homography",
    ) -> None:
        """``downscale``: shrink factor for the work image. ``min_distance_px``,
        ``ransac_reproj_px`` and the Lucas-Kanade window are in downscaled pixels.
        ``border_frac``: image border excluded from feature detection on each side.
        ``lk_levels``: pyramid levels above the base; with an 11 px window, 3 levels follow
        motions of ~80 work pixels per frame. ``model``: see the module docstring.
        """
        if downscale < 1:
            raise ValueError(f"downscale must be >= 1 (got {downscale})")
        if model not in ("homography", "affine"):
            raise ValueError(f"model must be 'homography' or 'affine' (got {model!r})")
        self.model = model
        self.downscale = int(downscale)
        self.max_features = int(max_features)
        self.min_distance_px = float(min_distance_px)
        self.quality_level = float(quality_level)
        self.border_frac = float(border_frac)
        self.ransac_reproj_px = float(ransac_reproj_px)
        self.lk_window_px = int(lk_window_px)
        self.lk_levels = int(lk_levels)
        self._prev_gray: NDArray[np.uint8] | None = None
        self._prev_pts: NDArray[np.float32] | None = None
        #: Inlier count of the last estimate (0 when it fell back to identity).
        self.last_inliers = 0

    def reset(self) -> None:
        """Forget the previous frame (after a gap in the stream)."""
        self._prev_gray = None
        self._prev_pts = None

    def _gray(self, image_rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
        if image_rgb.ndim == 3 and image_rgb.shape[2] == 3:
            gray = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY)
        elif image_rgb.ndim == 2:
            gray = image_rgb
        else:
            raise FrameError(f"CMC needs an (H, W, 3) RGB or (H, W) grey image (got {image_rgb.shape})")
        if self.downscale > 1:
            h, w = gray.shape
            gray = cv2.resize(gray, (w // self.downscale, h // self.downscale),
                              interpolation=cv2.INTER_AREA)
        return np.asarray(gray, dtype=np.uint8)

    def _features(
        self, gray: NDArray[np.uint8], boxes_xyxy_px: NDArray[np.float64]
    ) -> NDArray[np.float32] | None:
        h, w = gray.shape
        mask = np.zeros((h, w), np.uint8)
        bh, bw = int(round(h * self.border_frac)), int(round(w * self.border_frac))
        mask[bh:h - bh, bw:w - bw] = 255
        if boxes_xyxy_px.size:
            b = np.round(boxes_xyxy_px / self.downscale).astype(np.int64)
            b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, w)
            b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0, h)
            for u0, v0, u1, v1 in b:
                mask[v0:v1, u0:u1] = 0
        pts = cv2.goodFeaturesToTrack(
            gray, maxCorners=self.max_features, qualityLevel=self.quality_level,
            minDistance=self.min_distance_px, mask=mask, blockSize=3,
        )
        return None if pts is None else pts.astype(np.float32)

    def _fit(self, p0: NDArray[np.float32], p1: NDArray[np.float32], size_hw: tuple[int, int]) -> NDArray[np.float64] | None:
        """(3, 3) work-resolution motion fitted to point pairs, or None if not trustworthy."""
        if self.model == "homography":
            H, inliers = cv2.findHomography(p0, p1, cv2.RANSAC, self.ransac_reproj_px)
            n_in = int(inliers.sum()) if inliers is not None else 0
            # Perspective terms fitted to features in one corner extrapolate wildly: a
            # homography needs inliers spread over the image, else the similarity is safer.
            if (H is not None and n_in >= MIN_INLIERS
                    and _spread(p0[inliers.ravel().astype(bool)], size_hw) >= MIN_HOMOGRAPHY_SPREAD
                    and _plausible(np.asarray(H, np.float64), size_hw)):
                self.last_inliers = n_in
                return H.astype(np.float64)
        A, inliers = cv2.estimateAffinePartial2D(
            p0, p1, method=cv2.RANSAC, ransacReprojThreshold=self.ransac_reproj_px,
        )
        n_in = int(inliers.sum()) if inliers is not None else 0
        if A is None or n_in < MIN_INLIERS:
            return None
        self.last_inliers = n_in
        return np.vstack([A.astype(np.float64), [0.0, 0.0, 1.0]])

    def apply(
        self, image_rgb: NDArray[np.uint8], boxes_xyxy_px: Sequence[Sequence[float]] | NDArray[np.float64] = ()
    ) -> NDArray[np.float64]:
        """(3, 3) motion from the previous frame to this one, in full-resolution pixels.

        ``image_rgb``: (H, W, 3) uint8 RGB (or (H, W) grey). ``boxes_xyxy_px``: (N, 4) object
        boxes in this frame, excluded from the features tracked into the next frame.
        """
        gray = self._gray(image_rgb)
        boxes = np.asarray(boxes_xyxy_px, dtype=np.float64).reshape(-1, 4)
        warp = IDENTITY.copy()
        self.last_inliers = 0
        prev_gray, prev_pts = self._prev_gray, self._prev_pts
        if prev_gray is not None and prev_gray.shape != gray.shape:
            log.warning("CMC: image size changed %s -> %s; motion reset", prev_gray.shape, gray.shape)
            prev_gray = None
        if prev_gray is not None and prev_pts is not None and len(prev_pts) >= MIN_INLIERS:
            lk: Any = cv2.calcOpticalFlowPyrLK  # stubs reject nextPts=None, the binding needs it
            nxt, status, _err = lk(
                prev_gray, gray, prev_pts, None,
                winSize=(self.lk_window_px, self.lk_window_px), maxLevel=self.lk_levels,
            )
            ok = status.reshape(-1).astype(bool)
            p0, p1 = prev_pts.reshape(-1, 2)[ok], nxt.reshape(-1, 2)[ok]
            if len(p0) >= MIN_INLIERS:
                H = self._fit(p0, p1, gray.shape)
                if H is not None:
                    # Work pixels -> full pixels: S H S^-1 with S = diag(d, d, 1).
                    d = float(self.downscale)
                    S, S_inv = np.diag([d, d, 1.0]), np.diag([1.0 / d, 1.0 / d, 1.0])
                    warp = S @ H @ S_inv
                    warp /= warp[2, 2]
        self._prev_gray = gray
        self._prev_pts = self._features(gray, boxes)
        return warp


def _plausible(H: NDArray[np.float64], size_hw: tuple[int, int]) -> bool:
    """False for homographies no frame-to-frame camera motion produces (folds, blow-ups)."""
    h, w = size_hw
    corners = np.array([[0.0, 0.0, 1.0], [w, 0.0, 1.0], [w, h, 1.0], [0.0, h, 1.0]])
    den = corners @ H[2]
    if not np.all(np.isfinite(H)) or np.any(den <= 0.0):
        return False
    p = (corners @ H[:2].T) / den[:, None]
    # Signed area of the warped image outline (shoelace): it must stay convex-ish and sized.
    x, y = p[:, 0], p[:, 1]
    area = 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    ratio = area / float(w * h)
    return 1.0 / MAX_AREA_CHANGE < ratio < MAX_AREA_CHANGE


def _spread(points: NDArray[np.float32], size_hw: tuple[int, int]) -> float:
    """Area of the (N, 2) points' bounding box as a fraction of the image."""
    if len(points) == 0:
        return 0.0
    lo, hi = points.min(axis=0), points.max(axis=0)
    return float((hi[0] - lo[0]) * (hi[1] - lo[1])) / float(size_hw[0] * size_hw[1])
