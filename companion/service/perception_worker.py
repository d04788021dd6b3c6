"""Perception off the event loop: detect -> track -> geometry -> map update on the newest frame.

:class:`PerceptionPipeline` drives the per-frame step (:class:`semmap.pipeline.MappingPipeline`,
the same step as the offline ``companion map``) and measures each stage. :class:`PerceptionWorker` feeds it from a
:class:`~companion.sources.stream.FrameStream` (bounded, drop-oldest) and runs each step in a
worker thread, so the event loop (setpoints, MAVLink, MQTT) never waits for perception and
perception always works on the newest frame. The semantic map is guarded by a lock: the
planner side reads costmaps through :meth:`PerceptionWorker.costmap`.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Self

import numpy as np

from companion.config import CompanionConfig
from companion.sources.base import FrameSource, WrappedSource
from companion.sources.stream import FrameStream
from semmap.costmap import Costmap, VerticalBand
from semmap.detection import Detector, detector_from_config
from semmap.detection.builtin import detector_vote_groups
from semmap.errors import FrameError
from semmap.objects import ObjectMap
from semmap.pipeline import MappingPipeline, step_aware_tracker
from semmap.semantic_map import SemanticMap, SemanticMapSettings
from semmap.types import Frame

log = logging.getLogger(__name__)

def flight_band(cfg: CompanionConfig) -> VerticalBand:
    """The vertical band the vehicle occupies at the planner's flight altitude."""
    return cfg.planner.band_at()


def semantic_map_settings(cfg: CompanionConfig) -> SemanticMapSettings:
    """The semantic map's settings for ``cfg`` (its scan band, classes, flight band, depth range)."""
    return SemanticMapSettings.from_config(cfg.map, cfg.classes, flight_band(cfg),
                                           cfg.camera.depth_min_m, cfg.camera.depth_max_m)


def new_object_map(cfg: CompanionConfig) -> ObjectMap:
    """An empty object map for ``cfg``, weighing class votes as its detector needs (a model
    class standing for several of ours votes for all of them)."""
    groups = detector_vote_groups(cfg.detector, [c.name for c in cfg.classes],
                                  real_camera=cfg.camera.is_real)
    return ObjectMap(cfg.classes, cfg.map, vote_groups=groups)


def new_semantic_map(cfg: CompanionConfig) -> SemanticMap:
    """An empty semantic map with an object map, configured from ``cfg``."""
    return SemanticMap(semantic_map_settings(cfg), new_object_map(cfg))


@dataclass
class StageTimings:
    """Per-stage durations (ms): the latest frame's and running sums for means."""

    latest_ms: dict[str, float] = field(default_factory=dict)
    sum_ms: dict[str, float] = field(default_factory=dict)
    max_ms: dict[str, float] = field(default_factory=dict)
    count: dict[str, int] = field(default_factory=dict)

    def add(self, stage: str, ms: float) -> None:
        self.latest_ms[stage] = ms
        self.sum_ms[stage] = self.sum_ms.get(stage, 0.0) + ms
        self.max_ms[stage] = max(self.max_ms.get(stage, 0.0), ms)
        self.count[stage] = self.count.get(stage, 0) + 1

    def summary(self) -> dict[str, dict[str, float]]:
        """{stage: {"mean_ms", "max_ms", "count"}} rounded for reports."""
        return {s: {"mean_ms": round(self.sum_ms[s] / self.count[s], 2), "max_ms": round(self.max_ms[s], 2),
                    "count": self.count[s]} for s in self.sum_ms}


#: A frame with less valid depth than this (fraction of pixels in range) is not mapped.
MIN_VALID_DEPTH_FRACTION = 0.2


def check_frame(frame: Frame, depth_min_m: float, depth_max_m: float) -> None:
    """Raise :class:`FrameError` for a frame that must not reach the map: wrong shapes, a
    non-finite pose, or too little depth within ``[depth_min_m, depth_max_m]`` (a corrupt or
    blinded frame would otherwise paint phantom obstacles)."""
    d = np.asarray(frame.depth_m)
    if d.ndim != 2 or frame.rgb.shape[:2] != d.shape:
        raise FrameError(f"frame {frame.index}: rgb {frame.rgb.shape} and depth {d.shape} do not match")
    if frame.T_map_camera is not None and not np.all(np.isfinite(frame.T_map_camera)):
        raise FrameError(f"frame {frame.index}: the camera pose is not finite")
    with np.errstate(invalid="ignore"):
        valid = float(np.mean((d >= depth_min_m) & (d <= depth_max_m)))
    if valid < MIN_VALID_DEPTH_FRACTION:
        raise FrameError(f"frame {frame.index}: only {100 * valid:.0f} % of the depth is valid "
                         f"(< {100 * MIN_VALID_DEPTH_FRACTION:.0f} %); not mapped")


class PerceptionPipeline:
    """The service's driver of the per-frame step (:class:`semmap.pipeline.MappingPipeline`) on
    a :class:`SemanticMap`: checks each frame, counts and times them; thread-safe via ``lock``.
    """

    def __init__(self, cfg: CompanionConfig, smap: SemanticMap, detector: Detector,
                 timings: StageTimings | None = None) -> None:
        self.cfg = cfg
        self.smap = smap
        self.lock = threading.Lock()
        self.step = MappingPipeline(smap, cfg.classes, cfg.geometry, step_aware_tracker(cfg.tracker), detector,
                                    depth_range_m=(cfg.camera.depth_min_m, cfg.camera.depth_max_m),
                                    map_lock=self.lock)
        self.timings = timings or StageTimings()
        self.frames_done = 0
        self.frames_failed = 0
        #: Frames skipped because they came without a pose (no telemetry at their time).
        self.frames_unposed = 0
        self.last_frame_s: float | None = None  # monotonic time of the last integrated frame

    @property
    def detector(self) -> Detector | None:
        return self.step.detector

    @classmethod
    def from_config(cls, cfg: CompanionConfig, smap: SemanticMap,
                    object_classes: Mapping[int, str] | None = None) -> Self:
        """The configured detector (``builtin:`` models from the package) and tracker.
        ``object_classes``: the simulator's object id -> class (only the oracle detector uses it)."""
        detector = detector_from_config(cfg.detector, [c.name for c in cfg.classes],
                                        object_classes=object_classes, seed=cfg.sim.seed,
                                        real_camera=cfg.camera.is_real)
        return cls(cfg, smap, detector)

    def process(self, frame: Frame) -> dict[str, float]:
        """Detect, track, measure objects and update the map with one frame; returns the
        stage durations in ms. A frame without a pose is skipped (empty dict)."""
        if frame.T_map_camera is None:
            self.frames_unposed += 1
            return {}
        check_frame(frame, *self.step.depth_range_m)
        result = self.step.register_frame(frame)
        for name, ms in result.stages_ms.items():
            self.timings.add(name, ms)
        self.frames_done += 1
        self.last_frame_s = time.monotonic()
        return result.stages_ms

    def costmap(self, band: VerticalBand | None = None) -> Costmap:
        """The map's costmap at ``band`` (a consistent snapshot)."""
        with self.lock:
            return self.smap.costmap(band)


class TimedSource(WrappedSource):
    """A frame source that remembers when each frame was read (its capture time)."""

    def __init__(self, inner: FrameSource) -> None:
        super().__init__(inner)
        self.read_mono_s: deque[tuple[int, float]] = deque(maxlen=64)

    def read(self) -> Frame | None:
        frame = self.inner.read()
        if frame is not None:
            self.read_mono_s.append((frame.index, time.monotonic()))
        return frame

    def capture_time(self, index: int) -> float | None:
        for i, t in reversed(self.read_mono_s):
            if i == index:
                return t
        return None


class TimedPipeline(PerceptionPipeline):
    """The perception pipeline, remembering the capture time of the newest integrated frame
    (the perception process reports it with the costmap)."""

    source: TimedSource | None = None
    capture_mono_s: float | None = None

    def process(self, frame: Frame) -> dict[str, float]:
        out = super().process(frame)
        if out and self.source is not None:
            self.capture_mono_s = self.source.capture_time(frame.index)
        return out


class PerceptionWorker:
    """Runs :class:`PerceptionPipeline` on the newest frame of ``source`` (async context manager).

    Frames are read by the stream's reader thread into a drop-oldest queue of
    ``queue_size``; each frame is processed in a worker thread. A failing frame (bad data,
    a detector error) is logged and skipped; the worker keeps running. ``stale_after_s``:
    :meth:`is_fresh` turns False when no frame was integrated for that long (camera lost).
    """

    def __init__(self, pipeline: PerceptionPipeline, source: FrameSource, *, rate_hz: float | None,
                 queue_size: int = 1, stale_after_s: float = 2.0) -> None:
        self.pipeline = pipeline
        self.stream = FrameStream(source, queue_size=queue_size, rate_hz=rate_hz)
        self.stale_after_s = stale_after_s
        self._task: asyncio.Task[None] | None = None
        #: Called after every frame, processed or skipped (the systemd watchdog's heartbeat).
        self.on_frame: Callable[[], None] | None = None

    async def __aenter__(self) -> PerceptionWorker:
        await self.stream.__aenter__()
        self._task = asyncio.create_task(self._run(), name="perception")
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            except Exception:  # noqa: BLE001 - already logged by _run; closing anyway
                pass
        await self.stream.aclose()

    @property
    def dropped_frames(self) -> int:
        return self.stream.dropped_frames

    def is_fresh(self) -> bool:
        """True while frames keep arriving and being integrated."""
        last = self.pipeline.last_frame_s
        return last is not None and time.monotonic() - last <= self.stale_after_s

    def costmap(self, band: VerticalBand | None = None) -> Costmap:
        return self.pipeline.costmap(band)

    async def _run(self) -> None:
        failures = 0
        async for frame in self.stream:
            try:
                await asyncio.to_thread(self.pipeline.process, frame)
            except Exception as exc:  # noqa: BLE001 - one bad frame must not stop perception
                failures += 1
                self.pipeline.frames_failed += 1
                if failures == 1 or failures % 50 == 0:
                    log.warning("perception: frame %d skipped (%d so far): %s", frame.index, failures, exc,
                                exc_info=not isinstance(exc, FrameError))
            if self.on_frame is not None:
                self.on_frame()
        log.info("perception: the frame source ended after %d frames", self.pipeline.frames_done)
