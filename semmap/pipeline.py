"""The per-frame mapping step: detect -> track -> observe objects -> integrate into the map.

:class:`MappingPipeline` owns the one sequence every consumer runs on a posed RGB-D frame (as
KISS-ICP's ``register_frame`` owns its step): the service's perception process, the offline
``companion map`` and the safety benchmark's lock-step loop drive it and do the I/O around it.

1. **detect**: the detector's boxes, or boxes handed in (a recorded detections file);
2. **track**: a :class:`~semmap.tracking.camera_steps.StepAwareTracker`, so video is tracked in
   the image and keyframes (camera steps too large for the image tracker) are associated in
   3D by the object map;
3. **observe**: the view's floor height (:func:`~semmap.floor.view_floor_height_m`; the map's z
   is up, so only the height is estimated), then :func:`~semmap.frame_objects.observe_frame`,
   every box with the others of the frame (touching furniture), each object's footprint,
   height and points in the map frame. A view without a floor measures no object and costs
   none a miss: its heights would be guesses;
4. **integrate**: :meth:`SemanticMap.integrate_frame`: the object map, the depth band scan into
   the grid, the layers.

It does no I/O. Only the integrate stage touches the map, under ``map_lock`` when the caller
reads the map from another thread (detection and geometry run outside it).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semmap.config import ClassConfig, GeometryConfig, TrackerConfig
from semmap.detection import Detector
from semmap.errors import MapError
from semmap.floor import view_floor_height_m
from semmap.frame_objects import observe_frame
from semmap.geometry import ObjectObservation
from semmap.ransac import Plane
from semmap.semantic_map import FrameIntegration, SemanticMap
from semmap.tracking.botsort import BoTSORT
from semmap.tracking.camera_steps import StepAwareTracker
from semmap.types import Detection, Frame, Track

log = logging.getLogger(__name__)

__all__ = ["STAGES", "FrameResult", "FrameTracker", "MappingPipeline", "OneTrackPerBox", "step_aware_tracker"]

#: The stages timed every frame, in order.
STAGES = ("detect", "track", "geometry", "grid")


class FrameTracker(Protocol):
    """Turns one frame's detections into tracks, knowing the camera pose."""

    def update(self, detections: Sequence[Detection], image_rgb: NDArray[np.uint8] | None,
               T_map_camera: NDArray[np.float64] | None) -> list[Track]: ...


class OneTrackPerBox:
    """A tracker for frames known to be keyframes: every box is a track of its own, and the
    object map associates them in 3D."""

    def __init__(self) -> None:
        self._ids = itertools.count(1)

    def update(self, detections: Sequence[Detection], image_rgb: NDArray[np.uint8] | None = None,
               T_map_camera: NDArray[np.float64] | None = None) -> list[Track]:
        return [Track(next(self._ids), d.xyxy_px, d.score, d.class_name) for d in detections]


def step_aware_tracker(cfg: TrackerConfig) -> StepAwareTracker:
    """BoT-SORT from ``cfg``, giving way to 3D association after camera steps it cannot follow."""
    return StepAwareTracker(BoTSORT.from_config(cfg))


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What one :meth:`MappingPipeline.register_frame` did, with each stage's duration (ms)."""

    detections: list[Detection]
    tracks: list[Track]
    observations: list[ObjectObservation]
    integration: FrameIntegration
    #: The view's floor height (map z, metres); None: no floor found, no object measured.
    floor_height_m: float | None
    stages_ms: dict[str, float] = field(default_factory=dict)


class MappingPipeline:
    """Detect, track, observe and integrate one posed frame into ``smap`` (module doc).

    ``detector``: None when every frame's detections are handed to :meth:`register_frame`.
    ``classes``: the object classes (the map's), ``depth_range_m``: the depth trusted for
    objects. ``map_lock``: held while the map changes. ``clock``: the stage timer (seconds).
    """

    def __init__(self, smap: SemanticMap, classes: Sequence[ClassConfig], geometry: GeometryConfig,
                 tracker: FrameTracker, detector: Detector | None = None,
                 depth_range_m: tuple[float, float] = (0.0, math.inf), seed: int = 0,
                 map_lock: AbstractContextManager[object] | None = None,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        if smap.object_map is None:
            raise MapError("the mapping pipeline needs a semantic map with an object map")
        self.smap = smap
        self.classes = {c.name: c for c in classes}
        self.geometry = geometry
        self.tracker = tracker
        self.detector = detector
        self.depth_range_m = depth_range_m
        self.map_lock = map_lock if map_lock is not None else contextlib.nullcontext()
        self.clock = clock
        self._rng = np.random.default_rng(seed)
        #: Views in which no floor was found (their objects were not measured).
        self.views_without_floor = 0

    def register_frame(self, frame: Frame, T_map_camera: NDArray[np.float64] | None = None,
                       detections: Sequence[Detection] | None = None) -> FrameResult:
        """Map one frame. ``T_map_camera`` (4, 4, optical camera -> map) defaults to the
        frame's; ``detections`` replaces the detector's for this frame. Raises
        :class:`MapError` for a frame without a pose or boxes without a detector, and for boxes
        of a class the map does not know."""
        T_pose = T_map_camera if T_map_camera is not None else frame.T_map_camera
        if T_pose is None:
            raise MapError(f"frame {frame.index}: no camera pose (T_map_camera) to map it with")
        T = np.asarray(T_pose, dtype=np.float64)
        t0 = self.clock()
        if detections is None:
            if self.detector is None:
                raise MapError(f"frame {frame.index}: no detections given and the pipeline has no detector")
            dets = list(self.detector.detect_frame(frame))
        else:
            dets = list(detections)
        unknown = sorted({d.class_name for d in dets} - set(self.classes))
        if unknown:
            raise MapError(f"frame {frame.index}: detections of unknown classes {unknown} "
                           f"(classes: {sorted(self.classes)})")
        t1 = self.clock()
        tracks = self.tracker.update(dets, frame.rgb, T)
        t2 = self.clock()
        floor_m = view_floor_height_m(frame.depth_m, frame.intrinsics, T, self.depth_range_m)
        obs: list[ObjectObservation] = []
        if floor_m is None:
            self.views_without_floor += 1
            log.debug("frame %d: no floor in view; its objects are not measured", frame.index)
        else:
            obs = observe_frame(frame.depth_m, frame.intrinsics, T, tracks, self.classes, self.geometry,
                                floor=Plane.horizontal(floor_m), depth_range_m=self.depth_range_m,
                                stamp_s=frame.stamp_s, rng=self._rng)
        t3 = self.clock()
        with self.map_lock:
            integration = self.smap.integrate_frame(frame, T_map_camera=T,
                                                    observations=obs if floor_m is not None else None)
        t4 = self.clock()
        stages = {name: 1e3 * (b - a)
                  for name, a, b in zip(STAGES, (t0, t1, t2, t3), (t1, t2, t3, t4), strict=True)}
        return FrameResult(dets, tracks, obs, integration, floor_m, stages)
