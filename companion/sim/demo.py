"""The simulated-world demo: a seeded room, a scripted flight through it, rendered RGB-D frames
and the ground-truth maps, written as pictures and a summary into an output folder.

The steps are separate functions (:func:`build_world`, :func:`render_flight`,
:func:`write_frame_pictures`, :func:`ground_truth_map_picture`) so the full-system demo can
reuse them and add its own stages between rendering and writing.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig, write_effective_config
from companion.errors import SimulationError
from companion.sim.groundtruth import metric_costmap, room_grid_spec, semantic_costmap
from companion.sim.render import RoomRenderer, renderer_from_config
from companion.sim.trajectory import Trajectory, check_clearance, doorway_transit
from companion.sim.world import Room
from companion.sources.sim import SimFrameSource, room_from_config
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION, Costmap
from semmap.types import Frame

log = logging.getLogger(__name__)

#: Pixels per grid cell in map pictures.
MAP_SCALE_PX = 4
_UNKNOWN_RGB = (150, 150, 150)
_FREE_RGB = (255, 255, 255)
_LETHAL_RGB = (0, 0, 0)
_PATH_RGB = (255, 140, 0)


@dataclass
class DemoResult:
    """What the demo wrote: the folder, every file by role, and the summary it saved."""

    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)
    summary: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SimWorld:
    """The simulated world of a config: room, renderer, and the flight through it."""

    room: Room
    renderer: RoomRenderer
    trajectory: Trajectory
    altitude_m: float


def build_world(cfg: CompanionConfig) -> SimWorld:
    """The seeded room of ``cfg.sim``, its renderer, and a doorway-to-doorway flight at the
    planner's flight altitude with a yaw sweep, keeping the planner's vehicle radius plus the
    largest class margin from everything in the vehicle's band."""
    room = room_from_config(cfg)
    altitude = cfg.planner.flight_altitude_m
    margin = max((c.margin_m for c in cfg.classes), default=0.0)
    clearance = cfg.planner.vehicle_radius_m + margin
    traj = doorway_transit(
        room, altitude, speed_m_s=0.5, yaw_sweep_rad=math.radians(35.0),
        clearance_required_m=clearance, min_clearance_m=cfg.planner.vehicle_radius_m + 0.05,
        vehicle_height_m=cfg.planner.vehicle_height_m, vertical_margin_m=cfg.planner.vertical_margin_m,
    )
    return SimWorld(room, renderer_from_config(room, cfg), traj, altitude)


def render_flight(cfg: CompanionConfig, world: SimWorld, n_frames: int) -> list[Frame]:
    """``n_frames`` frames evenly spaced in time along the flight, through the simulated
    camera source (the camera rides on the vehicle via ``cfg.camera.extrinsics``)."""
    if n_frames < 1:
        raise SimulationError(f"n_frames must be >= 1 (got {n_frames})")
    traj = world.trajectory
    stamps = traj.start_s + np.linspace(0.0, traj.duration_s, n_frames)
    it = iter(stamps.tolist())

    def provider() -> tuple[float, NDArray[np.float64]] | None:
        t = next(it, None)
        return None if t is None else (t, traj.T_map_body(t))

    source = SimFrameSource(world.renderer, provider, cfg.camera.extrinsics.T_body_camera())
    with source:
        return list(source)


# --- pictures ---------------------------------------------------------------------------

def depth_picture(depth_m: NDArray[np.floating], max_m: float) -> NDArray[np.uint8]:
    """(H, W, 3) RGB: depth colourised near = red .. far = blue (TURBO), invalid black."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0)
    scaled = np.clip(255.0 * (1.0 - d / max_m), 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    bgr[d <= 0] = 0
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def mask_overlay_picture(
    frame: Frame, class_colors: Sequence[tuple[int, int, int]], class_names: Sequence[str],
    alpha: float = 0.55,
) -> NDArray[np.uint8]:
    """(H, W, 3) RGB: the colour image tinted by class, each instance outlined and labelled
    ``class #id`` at its mask's top-left."""
    rgb = frame.rgb.astype(np.float32)
    cls = frame.masks["class"].astype(np.int64)
    inst = np.asarray(frame.masks["instance"], dtype=np.int32)
    lut = np.array(list(class_colors) + [(0, 0, 0)], dtype=np.float32)  # -1 -> last row
    tint = lut[np.where(cls >= 0, cls, len(class_colors))]
    has = (cls >= 0)[..., None]
    out = np.where(has, (1 - alpha) * rgb + alpha * tint, rgb).clip(0, 255).astype(np.uint8)
    for oid in np.unique(inst[inst > 0]).tolist():
        m = (inst == oid).astype(np.uint8)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, (255, 255, 255), 1)
        vv, uu = np.nonzero(m)
        c = int(cls[vv[0], uu[0]])
        label = f"{class_names[c] if 0 <= c < len(class_names) else '?'} #{oid}"
        _label(out, label, (int(uu.min()), max(12, int(vv.min()) - 3)))
    return out


def _label(img: NDArray[np.uint8], text: str, org: tuple[int, int], scale: float = 0.45) -> None:
    """White text with a dark outline (readable on any background), in place."""
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def costmap_picture(
    costmap: Costmap, class_colors: Sequence[tuple[int, int, int]] | None = None,
    scale_px: int = MAP_SCALE_PX,
) -> NDArray[np.uint8]:
    """(rows*scale, cols*scale, 3) RGB, north up: free white, unknown grey, lethal black,
    cells with a class (``costmap.class_index``) in that class's colour."""
    cost = costmap.cost
    img = np.empty((*cost.shape, 3), dtype=np.uint8)
    img[:] = _UNKNOWN_RGB
    img[cost == FREE_SPACE] = _FREE_RGB
    soft = (cost > FREE_SPACE) & (cost < LETHAL_OBSTACLE)
    img[soft] = (255 - (cost[soft].astype(np.int32) * 200 // 253)).astype(np.uint8)[:, None]
    img[cost == LETHAL_OBSTACLE] = _LETHAL_RGB
    img[cost == NO_INFORMATION] = _UNKNOWN_RGB
    if class_colors is not None and costmap.class_index is not None:
        ci = costmap.class_index
        for k, col in enumerate(class_colors):
            img[ci == k] = col
    img = img[::-1]  # row 0 is the southern edge; pictures put north up
    big = cv2.resize(img, (img.shape[1] * scale_px, img.shape[0] * scale_px), interpolation=cv2.INTER_NEAREST)
    return np.asarray(big, dtype=np.uint8)


def _to_px(costmap: Costmap, xy_m: NDArray[np.floating], scale_px: int) -> NDArray[np.int32]:
    """(N, 2) map metres -> (N, 2) picture pixels (x right, y down, north up)."""
    spec = costmap.spec
    xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    col = (xy[:, 0] - spec.origin_xy_m[0]) / spec.resolution_m
    row_from_top = spec.rows - (xy[:, 1] - spec.origin_xy_m[1]) / spec.resolution_m
    return np.round(np.stack([col, row_from_top], axis=1) * scale_px).astype(np.int32)


def ground_truth_map_picture(
    cfg: CompanionConfig, world: SimWorld, path_xy_m: NDArray[np.floating] | None = None,
    scale_px: int = MAP_SCALE_PX,
) -> tuple[NDArray[np.uint8], dict[str, Costmap]]:
    """Side by side: the semantic costmap at the flight altitude (objects' whole footprints
    in class colours, labelled) and the metric slice a plain 2D map sees at that height
    (only legs), with the flight path. Returns (RGB picture, {"semantic", "metric"})."""
    room = world.room
    names = [c.name for c in cfg.classes]
    colors = [c.color_rgb for c in cfg.classes]
    spec = room_grid_spec(room, cfg.map.resolution_m)
    band = cfg.planner.band_at(world.altitude_m)
    sem = semantic_costmap(room, spec, band, class_names=names)
    met = metric_costmap(room, spec, world.altitude_m)
    panels = []
    for title, cm, colored in (
        (f"semantic costmap at {world.altitude_m:.2f} m (band {band.z_min_m:.2f}-{band.z_max_m:.2f} m)", sem, True),
        (f"metric slice at {world.altitude_m:.2f} m (what a 2D map sees)", met, False),
    ):
        img = costmap_picture(cm, colors if colored else None, scale_px)
        if path_xy_m is not None and len(path_xy_m) >= 2:
            cv2.polylines(img, [_to_px(cm, path_xy_m, scale_px)], False, _PATH_RGB, 2, cv2.LINE_AA)
        for obj in room.objects:
            fp = _to_px(cm, obj.footprint_xy_m(), scale_px)
            cv2.polylines(img, [fp], True, (90, 90, 90), 1, cv2.LINE_AA)
            if colored:
                cx, cy = _to_px(cm, np.array(obj.center_xy_m), scale_px)[0]
                _label(img, f"{obj.class_name} #{obj.object_id}", (int(cx) - 30, int(cy) + 4), 0.4)
        bar = np.full((26, img.shape[1], 3), 255, dtype=np.uint8)
        cv2.putText(bar, title, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        panels.append(np.vstack([bar, img]))
    gap = np.full((panels[0].shape[0], 8, 3), 255, dtype=np.uint8)
    picture = np.hstack([panels[0], gap, panels[1]])
    return np.vstack([picture, _legend(names, colors, picture.shape[1])]), {"semantic": sem, "metric": met}


def _legend(names: Sequence[str], colors: Sequence[tuple[int, int, int]], width_px: int) -> NDArray[np.uint8]:
    entries = [*zip(names, colors, strict=True), ("wall / slice hit", _LETHAL_RGB),
               ("free", _FREE_RGB), ("unknown", _UNKNOWN_RGB), ("flight path", _PATH_RGB)]
    per_row = max(1, width_px // 170)
    rows = math.ceil(len(entries) / per_row)
    img = np.full((rows * 22 + 6, width_px, 3), 255, dtype=np.uint8)
    for i, (name, col) in enumerate(entries):
        x, y = 8 + (i % per_row) * 170, 6 + (i // per_row) * 22
        cv2.rectangle(img, (x, y), (x + 14, y + 14), tuple(int(c) for c in col), -1)
        cv2.rectangle(img, (x, y), (x + 14, y + 14), (0, 0, 0), 1)
        cv2.putText(img, name, (x + 20, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def write_png(path: Path, rgb: NDArray[np.uint8]) -> Path:
    """Write an RGB picture as PNG; raises :class:`SimulationError` if it cannot."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise SimulationError(f"{path}: cannot write picture")
    return path


def write_frame_pictures(
    cfg: CompanionConfig, frame: Frame, out_dir: Path, stem: str,
) -> dict[str, Path]:
    """``<stem>_rgb.png``, ``<stem>_depth.png`` and ``<stem>_masks.png`` of one frame."""
    names = [c.name for c in cfg.classes]
    colors = [c.color_rgb for c in cfg.classes]
    return {
        "rgb": write_png(out_dir / f"{stem}_rgb.png", frame.rgb),
        "depth": write_png(out_dir / f"{stem}_depth.png", depth_picture(frame.depth_m, cfg.camera.depth_max_m)),
        "masks": write_png(out_dir / f"{stem}_masks.png", mask_overlay_picture(frame, colors, names)),
    }


# --- the whole demo ---------------------------------------------------------------------

def run_demo(
    cfg: CompanionConfig, out_dir: str | Path, n_frames: int = 40, n_pictures: int = 4,
) -> DemoResult:
    """Build the world of ``cfg``, fly it, render ``n_frames`` frames and write
    ``n_pictures`` of them, the ground-truth map picture, the effective config and
    ``summary.json`` into ``out_dir``. Returns what was written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out)
    t0 = time.perf_counter()
    world = build_world(cfg)
    log.info("room seed %d: %.1f x %.1f m, %d objects, flight %.1f s at %.2f m", world.room.seed,
             world.room.width_m, world.room.depth_m, len(world.room.objects),
             world.trajectory.duration_s, world.altitude_m)
    t_render = time.perf_counter()
    frames = render_flight(cfg, world, n_frames)
    render_s = time.perf_counter() - t_render
    log.info("rendered %d frames in %.1f s", len(frames), render_s)

    result.files["config"] = write_effective_config(cfg, out)
    picks = np.unique(np.linspace(0, len(frames) - 1, min(n_pictures, len(frames))).round().astype(int))
    for i in picks.tolist():
        for role, path in write_frame_pictures(cfg, frames[i], out / "frames", f"frame_{i:04d}").items():
            result.files[f"frame_{i:04d}_{role}"] = path
    path_xy = world.trajectory.positions_m(10.0)[:, :2]
    picture, maps = ground_truth_map_picture(cfg, world, path_xy)
    result.files["ground_truth_map"] = write_png(out / "ground_truth_map.png", picture)

    visible = [world.renderer.visible_objects(f, cfg.detector.oracle_min_visible_px) for f in frames]
    seen_ids = sorted({v.object_id for vs in visible for v in vs})
    room = world.room
    result.summary = {
        "seed": room.seed,
        "room_m": {"width": room.width_m, "depth": room.depth_m, "wall_height": room.wall_height_m},
        "doorways": [{"center_xy_m": list(d.center_xy_m), "width_m": d.width_m, "wall": d.wall}
                     for d in room.doorways],
        "objects": [
            {"id": o.object_id, "class": o.class_name, "center_xy_m": [round(v, 3) for v in o.center_xy_m],
             "yaw_deg": round(math.degrees(o.yaw_rad), 1), "size_m": [round(v, 3) for v in o.size_m],
             "seen": o.object_id in seen_ids}
            for o in room.objects
        ],
        "flight": {
            "altitude_m": world.altitude_m, "duration_s": round(world.trajectory.duration_s, 2),
            "min_clearance_m": round(check_clearance(
                room, world.trajectory, 0.0, cfg.planner.vehicle_height_m, cfg.planner.vertical_margin_m), 3),
        },
        "frames": {
            "rendered": len(frames),
            "render_ms_mean": round(1e3 * render_s / max(1, len(frames)), 1),
            "visible_objects_mean": round(float(np.mean([len(v) for v in visible])), 2),
            "valid_depth_fraction_mean": round(float(np.mean([(f.depth_m > 0).mean() for f in frames])), 3),
        },
        "ground_truth_map": {
            "resolution_m": maps["semantic"].spec.resolution_m,
            "semantic_lethal_cells": int(maps["semantic"].lethal.sum()),
            "metric_lethal_cells": int(maps["metric"].lethal.sum()),
        },
        "elapsed_s": round(time.perf_counter() - t0, 2),
    }
    summary_path = out / "summary.json"
    result.files["summary"] = summary_path
    result.summary["files"] = {k: str(p.relative_to(out)) for k, p in sorted(result.files.items())}
    summary_path.write_text(json.dumps(result.summary, indent=2) + "\n", encoding="utf-8")
    log.info("demo outputs in %s", out)
    return result
