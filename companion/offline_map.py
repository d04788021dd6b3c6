"""Build a semantic map offline from a recorded RGB-D folder (``companion map``).

The same per-frame step as the service (:class:`semmap.pipeline.MappingPipeline`) on
detections from a detector model or a detections file: tracks (BoT-SORT giving way to 3D
association after large camera steps, or one track per box), per-object geometry, the object
map, the depth band scan into the grid, the layers. Recorded poses are
camera-to-world in the recording's own world frame (for the dining room, roughly the first
camera's optical frame, floor tilted), so the floor is estimated first (RANSAC, the lowest
large near-horizontal plane) and a gravity-aligned map frame built on it: z up, floor at 0.

Outputs (see :func:`semmap.export.export_all`): ``map.pgm/.yaml``, ``costmap.pgm/.yaml``,
``map.png``, ``objects.json`` (and ``objects.geojson`` with a geographic origin),
``semantic_map.npz`` and the effective ``config.yaml``.

A detections file is JSON ``{"frames": {"<colour file name>": [{"class": str, "score":
float, "xyxy": [u0, v0, u1, v1]}, ...]}}`` (the format of
``../shared/data/rgbd/diningroom/detections_yolox_nano.json``). Its class names are the
detector's (COCO); ``detector.class_map`` maps them to ours, or, when empty,
:data:`COCO_TO_CLASSES` does.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig, write_effective_config
from companion.sources.recorded import RecordedFrameSource
from semmap.detection import Detector, detector_from_config
from semmap.detection.builtin import detector_vote_groups, vote_groups
from semmap.errors import ConfigError, DataError, FrameError, MapError
from semmap.export import export_all
from semmap.frames import transform_points
from semmap.objects import ObjectMap
from semmap.pipeline import MappingPipeline, OneTrackPerBox, step_aware_tracker
from semmap.pointcloud import backproject
from semmap.ransac import estimate_floor, gravity_aligned_frame
from semmap.semantic_map import SemanticMap, SemanticMapSettings
from semmap.tracking.camera_steps import StepAwareTracker
from semmap.types import Detection

log = logging.getLogger(__name__)

#: COCO detector names -> our classes, used for detections files when ``detector.class_map``
#: is empty. COCO's one table class votes for our three; the geometric prior chooses.
COCO_TO_CLASSES: dict[str, str | list[str]] = {
    "chair": "chair", "couch": "sofa", "dining table": ["desk", "coffee_table", "conference_table"]}

#: Called after each frame with (frames done, frames total).
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class OfflineMapOptions:
    """How to build the map. ``detections_path``: a detections file instead of the config's
    detector. ``use_tracker``: BoT-SORT across frames (off for sparse keyframes: each box is
    its own track and the object map re-associates by footprint). ``align_floor``: estimate
    the floor; off when the recording's world is already z-up with the floor at 0.
    ``geo_origin_lat_lon_deg``: the map origin's WGS-84 position for GeoJSON.
    ``max_frames``: stop after this many frames. ``floor_sample_frames``: frames pooled for
    the floor estimate."""

    detections_path: Path | None = None
    use_tracker: bool = True
    align_floor: bool = True
    geo_origin_lat_lon_deg: tuple[float, float] | None = None
    max_frames: int | None = None
    floor_sample_frames: int = 12


@dataclass(frozen=True, eq=False)
class OfflineMapResult:
    """What :func:`build_offline_map` produced."""

    semantic_map: SemanticMap
    object_map: ObjectMap
    T_map_world: NDArray[np.float64]
    frames_used: int
    frames_skipped: int
    files: dict[str, Path] = field(default_factory=dict)


def load_detections_file(
    path: Path, class_names: Sequence[str], class_map: Mapping[str, str | list[str]] | None = None,
    score_threshold: float = 0.0,
) -> dict[str, list[Detection]]:
    """Detections per colour file name, mapped to our classes (others dropped; a list target
    reports its first class, see :func:`detections_class_map`).

    Raises :class:`DataError` naming the file and the bad entry.
    """
    mapping = {k: v if isinstance(v, str) else v[0]
               for k, v in detections_class_map(class_names, class_map).items()}
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise DataError(f"{path}: detections file not found") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not a readable JSON detections file ({exc})") from exc
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, dict):
        raise DataError(f"{path}: expected an object with a 'frames' mapping (file name -> boxes)")
    out: dict[str, list[Detection]] = {}
    for name, boxes in frames.items():
        if not isinstance(boxes, list):
            raise DataError(f"{path}: frames[{name!r}] must be a list of boxes")
        dets = []
        for j, b in enumerate(boxes):
            where = f"{path}: frames[{name!r}][{j}]"
            try:
                cls, score, xyxy = str(b["class"]), float(b["score"]), [float(v) for v in b["xyxy"]]
            except (KeyError, TypeError, ValueError) as exc:
                raise DataError(f"{where}: needs 'class', 'score' and 'xyxy' ({exc})") from exc
            if len(xyxy) != 4 or xyxy[2] <= xyxy[0] or xyxy[3] <= xyxy[1]:
                raise DataError(f"{where}: xyxy must be [u0, v0, u1, v1] with u1 > u0, v1 > v0")
            target = mapping.get(cls)
            if target is None or score < score_threshold:
                continue
            dets.append(Detection((xyxy[0], xyxy[1], xyxy[2], xyxy[3]), score, target))
        out[str(name)] = sorted(dets, key=lambda d: -d.score)
    return out


def detections_class_map(
    class_names: Sequence[str], class_map: Mapping[str, str | list[str]] | None = None,
) -> dict[str, str | list[str]]:
    """The class map a detections file is read with: the config's, else
    :data:`COCO_TO_CLASSES` restricted to the configured classes. Raises
    :class:`ConfigError` for a configured target that is not a class."""
    if class_map:
        targets = {t for v in class_map.values() for t in ([v] if isinstance(v, str) else v)}
        bad = sorted(t for t in targets if t not in class_names)
        if bad:
            raise ConfigError(f"detector.class_map maps to unknown classes {bad} (classes: {list(class_names)})")
        return dict(class_map)
    out: dict[str, str | list[str]] = {}
    for k, v in COCO_TO_CLASSES.items():
        kept = [t for t in ([v] if isinstance(v, str) else v) if t in class_names]
        if kept:
            out[k] = kept if isinstance(v, list) else kept[0]
    return out


def estimate_map_alignment(
    source: RecordedFrameSource, depth_range_m: tuple[float, float], n_frames: int = 12,
) -> NDArray[np.float64]:
    """``T_map_world`` (4, 4): a gravity-aligned map frame on the floor of the recording.

    Pools a subsampled cloud of up to ``n_frames`` evenly spaced posed frames in the world
    frame; "up" starts as the first camera's -y (a roughly level camera). The map x axis
    follows the first camera's viewing direction. Raises :class:`MapError` without a floor.
    """
    n = len(source)
    picks = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, max(1, n_frames)))})
    clouds, first_R = [], None
    for i in picks:
        f = source.frame_at(i)
        if f.T_map_camera is None:
            continue
        T = np.asarray(f.T_map_camera, np.float64)
        first_R = T[:3, :3] if first_R is None else first_R
        pts, _ = backproject(f.depth_m, f.intrinsics, *depth_range_m, stride_px=4)
        clouds.append(transform_points(T, pts))
    if first_R is None or not clouds:
        raise DataError(f"{source.path}: no frame has a pose; the offline map needs camera poses")
    up_hint = first_R @ np.array([0.0, -1.0, 0.0])
    forward = first_R @ np.array([0.0, 0.0, 1.0])
    floor = estimate_floor(np.concatenate(clouds), up_hint=up_hint, rng=np.random.default_rng(0))
    return gravity_aligned_frame(floor.plane, forward_hint=(float(forward[0]), float(forward[1]), float(forward[2])))


def build_offline_map(
    sequence: str | Path, out_dir: str | Path, cfg: CompanionConfig,
    options: OfflineMapOptions | None = None, progress: Progress | None = None,
) -> OfflineMapResult:
    """Map a recorded folder into ``out_dir`` (see the module docstring). Frames that cannot
    be read are skipped with a warning; a recording without poses is an error."""
    opts = options or OfflineMapOptions()
    out = Path(out_dir)
    class_names = [c.name for c in cfg.classes]
    cam = cfg.camera
    depth_range = (cam.depth_min_m, cam.depth_max_m)
    source = RecordedFrameSource(sequence, default_intrinsics=cam.intrinsics(), depth_min_m=cam.depth_min_m,
                                 depth_max_m=cam.depth_max_m, rate_hz=cam.rate_hz)
    source.open()
    n_total = len(source) if opts.max_frames is None else min(len(source), opts.max_frames)
    if n_total == 0:
        raise DataError(f"{sequence}: the recording has no frames")

    detections, detector = _detection_input(cfg, opts, class_names)

    T_map_world = (estimate_map_alignment(source, depth_range, opts.floor_sample_frames)
                   if opts.align_floor else np.eye(4))
    band = cfg.planner.band_at()
    settings = SemanticMapSettings.from_config(cfg.map, cfg.classes, band, *depth_range)
    groups = (vote_groups(detections_class_map(class_names, cfg.detector.class_map)) if detections is not None
              else detector_vote_groups(cfg.detector, class_names, real_camera=True))
    omap = ObjectMap(cfg.classes, cfg.map, vote_groups=groups)
    smap = SemanticMap(settings, omap)
    # Keyframes (camera steps beyond what BoT-SORT follows) are associated in 3D by the object map.
    tracker = step_aware_tracker(cfg.tracker) if opts.use_tracker else OneTrackPerBox()
    pipeline = MappingPipeline(smap, cfg.classes, cfg.geometry, tracker, detector, depth_range_m=depth_range)
    used, skipped = _register_frames(source, n_total, T_map_world, detections, pipeline, progress)
    source.close()
    if used == 0:
        raise DataError(f"{sequence}: no usable frame (all unreadable or without pose)")
    colours = {c.name: c.color_rgb for c in cfg.classes}
    files = export_all(out, smap, colours, opts.geo_origin_lat_lon_deg)
    files["config"] = write_effective_config(cfg, out)
    log.info("mapped %d frames (%d skipped): %d objects, grid %dx%d", used, skipped, len(smap.objects),
             *smap.spec.shape_rc)
    if isinstance(tracker, StepAwareTracker) and tracker.steps:
        log.info("%d of %d frames followed a camera step too large to track in the image: associated in 3D",
                 tracker.steps, used)
    return OfflineMapResult(smap, omap, T_map_world, used, skipped, files)


def _detection_input(
    cfg: CompanionConfig, opts: OfflineMapOptions, class_names: list[str],
) -> tuple[dict[str, list[Detection]] | None, Detector | None]:
    """The recording's detections file (per image name), or else the configured detector."""
    if opts.detections_path is not None:
        # A detections file was already thresholded by whoever wrote it, unless the config says.
        return load_detections_file(Path(opts.detections_path), class_names, cfg.detector.class_map,
                                    cfg.detector.score_threshold or 0.0), None
    if cfg.detector.kind == "oracle":
        raise ConfigError("detector.kind 'oracle' needs the simulator; for a recording give "
                          "--detections FILE or configure detector.kind: onnx")
    return None, detector_from_config(cfg.detector, class_names, real_camera=True)


def _register_frames(
    source: RecordedFrameSource, n_total: int, T_map_world: NDArray[np.float64],
    detections: dict[str, list[Detection]] | None, pipeline: MappingPipeline, progress: Progress | None,
) -> tuple[int, int]:
    """Feed the first ``n_total`` posed, readable frames to ``pipeline`` in the map frame;
    returns (used, skipped)."""
    entries = source.entries
    used = skipped = 0
    for i in range(n_total):
        try:
            frame = source.frame_at(i)
        except FrameError as exc:
            log.warning("skipping frame %d: %s", i, exc)
            skipped += 1
            continue
        if frame.T_map_camera is None:
            log.warning("skipping frame %d (%s): no pose", i, entries[i].rgb_path.name)
            skipped += 1
            continue
        T = T_map_world @ np.asarray(frame.T_map_camera, np.float64)
        dets = detections.get(entries[i].rgb_path.name, []) if detections is not None else None
        pipeline.register_frame(frame, T, dets)
        used += 1
        if progress is not None:
            progress(i + 1, n_total)
    return used, skipped

def parse_lat_lon(text: str) -> tuple[float, float]:
    """``"LAT,LON"`` in degrees -> (lat, lon); raises :class:`ConfigError` when malformed."""
    try:
        lat_s, lon_s = text.split(",")
        lat, lon = float(lat_s), float(lon_s)
    except ValueError as exc:
        raise ConfigError(f"--geo-origin must be LAT,LON in degrees (got {text!r})") from exc
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or math.isnan(lat + lon):
        raise ConfigError(f"--geo-origin out of range (got {text!r})")
    return lat, lon


__all__ = ["COCO_TO_CLASSES", "MapError", "OfflineMapOptions", "OfflineMapResult", "build_offline_map",
           "detections_class_map", "estimate_map_alignment", "load_detections_file", "parse_lat_lon"]
