"""What the demo flights share, with the mock autopilot (:mod:`companion.sim.demo_e2e`) and
with a real PX4 (:mod:`companion.sim.demo_px4`): the flight's config, the room as geofence,
the crossing's upload with MAVSDK, and the outputs (map files, picture, ``summary.json``)."""

from __future__ import annotations

import contextlib
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from companion.errors import SimulationError
from companion.mavsdk_client import MavsdkClient
from companion.missions import MissionPlan, Waypoint
from companion.service.app import CompanionService
from companion.service.checkpoint import checkpoint_path
from companion.sim.sim_world import SimPlacement
from semmap.export import export_all, render_picture

log = logging.getLogger(__name__)


def flight_config(cfg: CompanionConfig, out: Path, link_url: str, broker_port: int | None) -> CompanionConfig:
    """``cfg`` for one demo flight: the service's link on ``link_url``, outputs and checkpoint
    in ``out``, the ground link on ``broker_port`` (off when None). A checkpoint an earlier run
    left there is removed: a demo flies a fresh room, maybe of another seed."""
    mqtt = cfg.mqtt.model_copy(update={"enabled": broker_port is not None, "port": broker_port or 1883})
    service = cfg.service.model_copy(update={"output_dir": str(out), "map_dir": str(out / "checkpoint")})
    cfg = cfg.model_copy(update={"mqtt": mqtt, "service": service,
                                 "link": cfg.link.model_copy(update={"url": link_url})})
    with contextlib.suppress(FileNotFoundError):
        checkpoint_path(cfg).unlink()
        log.info("removed the previous demo's map checkpoint in %s", out)
    return cfg


def with_room_geofence(cfg: CompanionConfig, placement: SimPlacement) -> CompanionConfig:
    """``cfg`` with the room as the planner's geofence unless it has one: the mission author
    knows the room's walls (not its furniture), so no leg is planned out of a doorway through
    unmapped space."""
    if cfg.planner.geofence_xy_m is not None:
        return cfg
    x0, y0 = placement.room_to_map_xy((0.0, 0.0))
    x1, y1 = placement.room_to_map_xy((placement.room.width_m, placement.room.depth_m))
    return cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"geofence_xy_m": (x0, y0, x1, y1)})})


async def upload_crossing(url: str, waypoints_map_xy: list[tuple[float, float]], altitude_m: float,
                          acceptance_m: float = 0.3, connect_timeout_s: float = 20.0) -> None:
    """Upload the demo's waypoints (map frame, at ``altitude_m``) with MAVSDK on ``url``."""
    plan = MissionPlan(tuple(Waypoint(xyz_map_m=(x, y, altitude_m), acceptance_radius_m=acceptance_m)
                             for x, y in waypoints_map_xy), None, "demo crossing")
    async with MavsdkClient(url, connect_timeout_s=connect_timeout_s) as client:
        await client.upload_mission(plan.resolved(await client.home(timeout_s=20.0)))
    log.info("mission of %d waypoints uploaded with MAVSDK", len(waypoints_map_xy))


def export_flight(out: Path, service: CompanionService, placement: SimPlacement,
                  path_map: NDArray[np.float64], wps_map: list[tuple[float, float]]) -> dict[str, Path]:
    """The flight's map files (``map_*``) and its picture with the flown path (``picture``)."""
    assert service.smap is not None
    colours = {c.name: c.color_rgb for c in service.cfg.classes}
    files = {f"map_{k}": v for k, v in export_all(out / "map", service.smap, colours).items()}
    files["picture"] = write_picture(out / "map_with_path.png", service, placement, path_map, wps_map)
    return files


def write_summary(out: Path, summary: dict[str, Any], files: dict[str, Path]) -> Path:
    """``summary.json`` in ``out``, listing ``files`` (and itself) relative to ``out``."""
    path = out / "summary.json"
    files["summary"] = path
    summary["files"] = {k: str(p.relative_to(out)) if p.is_relative_to(out) else str(p)
                        for k, p in sorted(files.items())}
    path.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return path


def write_picture(path: Path, service: CompanionService, placement: SimPlacement,
                   path_map: NDArray[np.float64], wps_map: list[tuple[float, float]]) -> Path:
    """The semantic map picture (objects) with the flown path, true footprints and waypoints."""
    assert service.smap is not None
    smap = service.smap
    img = render_picture(smap, {c.name: c.color_rgb for c in service.cfg.classes})
    h = img.shape[0]
    # A second panel in the room's own extent: the room, true footprints, mapped objects, path.
    room = placement.room
    pad = 0.5
    px_per_m = 80
    W = int((room.width_m + 2 * pad) * px_per_m)
    H = int((room.depth_m + 2 * pad) * px_per_m)
    panel = np.full((H, W, 3), 255, np.uint8)

    def to_px(xy_map: NDArray[np.floating]) -> NDArray[np.int32]:
        xy = np.asarray(xy_map, np.float64).reshape(-1, 2) + np.array(placement.offset_xy_m)
        return np.column_stack([(xy[:, 0] + pad) * px_per_m, H - (xy[:, 1] + pad) * px_per_m]).round().astype(np.int32)

    def room_px(xy_room: NDArray[np.floating]) -> NDArray[np.int32]:
        return to_px(np.asarray(xy_room, np.float64).reshape(-1, 2) - np.array(placement.offset_xy_m))

    cv2.rectangle(panel, tuple(room_px(np.array([0.0, 0.0]))[0]),
                  tuple(room_px(np.array([room.width_m, room.depth_m]))[0]), (0, 0, 0), 2)
    colours = {c.name: c.color_rgb for c in service.cfg.classes}
    # The room as laid out: clutter solid grey, true footprints tinted pale by class (tucked
    # chairs overlap their table), and a thin line from each arranged piece to its partner.
    for o in room.clutter:
        for part in o.parts:
            cv2.fillPoly(panel, [room_px(part.corners_xy_m())], (185, 185, 185), cv2.LINE_AA)
    tint = panel.copy()
    for o in room.objects:
        col = colours.get(o.class_name, (150, 150, 150))
        pale = tuple(int(255 - 0.35 * (255 - v)) for v in (col[2], col[1], col[0]))
        cv2.fillPoly(tint, [room_px(o.footprint_xy_m())], pale, cv2.LINE_AA)
    panel = np.minimum(panel, tint)
    for o in room.objects:
        cv2.polylines(panel, [room_px(o.footprint_xy_m())], True, (150, 150, 150), 1, cv2.LINE_AA)
    by_id = {o.object_id: o for o in room.objects}
    for rel in room.relations:
        if rel.b_id in by_id and rel.a_id in by_id:
            a, b = (room_px(np.array(by_id[i].center_xy_m))[0] for i in (rel.a_id, rel.b_id))
            cv2.line(panel, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), (120, 120, 120), 1, cv2.LINE_AA)
    for fp in smap.objects:
        col = colours.get(fp.class_name, (200, 0, 200))
        poly = to_px(np.asarray(fp.polygon_xy_m))
        cv2.polylines(panel, [poly], True, (int(col[2]), int(col[1]), int(col[0])), 2, cv2.LINE_AA)
        c = poly.mean(axis=0).astype(int)
        cv2.putText(panel, f"{fp.class_name} #{fp.object_id}", (int(c[0]) - 30, int(c[1])),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    if len(path_map) >= 2:
        cv2.polylines(panel, [to_px(path_map[:, :2])], False, (0, 140, 255), 2, cv2.LINE_AA)
    for i, wp in enumerate([(0.0, 0.0), *wps_map]):
        q = to_px(np.array(wp))[0]
        cv2.circle(panel, (int(q[0]), int(q[1])), 6, (0, 0, 255), 2)
        cv2.putText(panel, "start" if i == 0 else f"wp{i}", (int(q[0]) + 8, int(q[1]) - 8),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 255), 1, cv2.LINE_AA)
    cv2.putText(panel, "pale: true footprints (lines join groups), solid grey: clutter, colour: mapped objects, "
                "orange: flown path", (8, 18),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    # Side by side with the map picture (same height).
    ph = h
    pw = int(W * ph / H)
    panel = cv2.resize(panel, (pw, ph), interpolation=cv2.INTER_AREA)
    both = np.hstack([img, np.full((h, 8, 3), 255, np.uint8), panel])
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), both):
        raise SimulationError(f"{path}: cannot write picture")
    return path
