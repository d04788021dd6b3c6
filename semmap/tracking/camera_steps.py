"""Tracking across camera steps larger than an image tracker can follow.

BoT-SORT assumes video: boxes move a little between frames, and its camera-motion model is a
homography of the whole image. Between keyframes 0.2-0.7 m and tens of degrees apart the
parallax is far beyond that: boxes of one object fail to match (objects are lost) or match a
neighbour's box (a track id jumps metres onto another object). :class:`StepAwareTracker`
watches the camera pose: for a frame after a step larger than ``max_step_m`` or
``max_step_deg`` it resets the image tracker and gives every box a track id of its own, so the
object map associates it in 3D (footprint overlap, class) instead; otherwise it tracks as
usual. The first posed frame is handled like a step: the image tracker would drop its
low-scoring boxes until they repeat, while the object map weighs each box by its quality.
Its ids never repeat, and an image-tracker id is never continued across a step.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semmap.types import Detection, Track

__all__ = ["ImageTracker", "StepAwareTracker", "camera_step"]


class ImageTracker(Protocol):
    def update(self, detections: Sequence[Detection], image_rgb: NDArray[np.uint8] | None = None) -> list[Track]: ...

    def reset(self) -> None: ...


def camera_step(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> tuple[float, float]:
    """(translation m, rotation deg) between two camera poses (4, 4) in one frame."""
    d = float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]))
    R = T_a[:3, :3].T @ T_b[:3, :3]
    c = (float(np.trace(R)) - 1.0) / 2.0
    return d, math.degrees(math.acos(min(1.0, max(-1.0, c))))


class StepAwareTracker:
    """An image tracker that gives way to 3D association after large camera steps (module doc).

    ``max_step_m`` / ``max_step_deg``: the largest camera motion between two frames the image
    tracker follows (at 15 Hz a drone moves about 0.07 m and turns a few degrees per frame).
    """

    def __init__(self, tracker: ImageTracker, max_step_m: float = 0.15, max_step_deg: float = 10.0) -> None:
        self.tracker = tracker
        self.max_step_m = max_step_m
        self.max_step_deg = max_step_deg
        self._ids = itertools.count(1)
        self._of_image_track: dict[int, int] = {}
        self._last_T: NDArray[np.float64] | None = None
        #: Frames handled as keyframes (after a large step), for the log and tests.
        self.steps = 0

    def update(self, detections: Sequence[Detection], image_rgb: NDArray[np.uint8] | None,
               T_map_camera: NDArray[np.float64] | None) -> list[Track]:
        """This frame's tracks. ``T_map_camera`` (4, 4) or None (unknown: treated as video)."""
        step = False
        if T_map_camera is not None:
            T = np.asarray(T_map_camera, dtype=np.float64)
            if self._last_T is None:
                step = True  # the first frame has no image history either: every box counts
            else:
                d_m, d_deg = camera_step(self._last_T, T)
                step = d_m > self.max_step_m or d_deg > self.max_step_deg
            self._last_T = T
        if step:
            self.steps += 1
            self.tracker.reset()
            self._of_image_track.clear()
            # The image tracker starts over from this frame (for the video that may follow),
            # but this frame's boxes are each a track of their own.
            self.tracker.update(detections, image_rgb)
            self._of_image_track.clear()
            return [Track(next(self._ids), d.xyxy_px, d.score, d.class_name) for d in detections]
        out = []
        for t in self.tracker.update(detections, image_rgb):
            tid = self._of_image_track.get(t.track_id)
            if tid is None:
                tid = self._of_image_track[t.track_id] = next(self._ids)
            out.append(Track(tid, t.xyxy_px, t.score, t.class_name))
        return out
