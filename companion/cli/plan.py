"""``companion plan --map DIR --start X,Y --goal X,Y --out path.png``: plan on a saved map.

The map folder is what ``semmap.export.export_all`` writes. With ``semantic_map.npz`` the
planner gets the semantic costmap at the flight altitude (objects blocking by the altitude
rule). Without it, the ROS ``map.yaml``/``map.pgm`` occupancy is read the way map_server does
(occupied/free thresholds from the YAML), and the objects in ``objects.json`` (if present)
are added by the altitude rule. Exit code 0 with a path, 1 when there is none (the reason
is printed), 2 for bad arguments or an unreadable map.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import load_config
from companion.errors import DataError, MapError
from planner.config import PlannerConfig
from planner.planner import Planner
from planner.types import PlanResult
from semmap.costmap import (
    FREE_SPACE,
    LETHAL_OBSTACLE,
    MAX_NON_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    ObjectFootprint,
    VerticalBand,
)
from semmap.layers import paint_objects

log = logging.getLogger(__name__)

#: A negative number, or an X,Y pair starting with one: a value, not an option.
_NUMBER = r"-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NEGATIVE_XY = re.compile(rf"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?:,{_NUMBER})?$")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("plan", help="plan a path on a saved map and draw it")
    p.add_argument("--map", required=True, metavar="DIR",
                   help="map folder (semantic_map.npz, or map.yaml + map.pgm [+ objects.json])")
    p.add_argument("--start", required=True, type=_xy_arg, metavar="X,Y",
                   help="start, map frame, metres (negative too: --start -3.9,1.3)")
    p.add_argument("--goal", required=True, type=_xy_arg, metavar="X,Y", help="goal, map frame, metres")
    p.add_argument("--out", default=None, metavar="PNG", help="picture of the map and the path")
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--altitude", type=float, default=None, metavar="M", help="flight altitude, metres")
    p.add_argument("--algorithm", default=None, help="OMPL planner (overrides the config)")
    p.add_argument("--time-limit", type=float, default=None, metavar="S", help="planning budget, seconds")
    p.add_argument("--snap", action="store_true", help="snap a bad goal to the nearest reachable free point")
    p.add_argument("--source", choices=["auto", "semantic", "ros"], default="auto",
                   help="which map file to plan on (default: semantic_map.npz if present)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    # argparse takes "-3.9,1.3" for an option (only "-3.9" looks like a number to it): let
    # negative X,Y pairs be values, as the help shows them.
    p._negative_number_matcher = _NEGATIVE_XY  # noqa: SLF001 - argparse has no public hook
    p.set_defaults(func=_run)


def _xy_arg(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres (e.g. 1.5,-2), got {text!r}") from exc
    if not (np.isfinite(x) and np.isfinite(y)):
        raise argparse.ArgumentTypeError(f"coordinates must be finite, got {text!r}")
    return x, y


def _json_safe(value: object) -> object:
    """``value`` with numpy scalars as Python numbers and NaN/infinity as None (JSON null):
    ``NaN`` is not JSON, and a ground tool's parser rejects it."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def costmap_from_ros_occupancy(occupancy: NDArray[np.int8], spec: object, band: VerticalBand) -> Costmap:
    """nav_msgs values (rows, cols) in grid order -> a Costmap: 100 lethal, -1 unknown, 0 free,
    1..99 soft costs scaled into FREE_SPACE..MAX_NON_OBSTACLE."""
    occ = np.asarray(occupancy)
    cost = np.full(occ.shape, NO_INFORMATION, dtype=np.uint8)
    cost[occ == 0] = FREE_SPACE
    soft = (occ > 0) & (occ < 100)
    cost[soft] = np.rint(occ[soft].astype(np.float64) / 100.0 * MAX_NON_OBSTACLE).astype(np.uint8)
    cost[occ >= 100] = LETHAL_OBSTACLE
    return Costmap(spec, cost, band)  # type: ignore[arg-type]


def load_map(
    folder: Path, band: VerticalBand, source: str, class_margins_m: Mapping[str, float] | None = None,
) -> tuple[Costmap, str]:
    """The costmap at ``band`` from a map folder, and a description of what was read; objects
    listed without a margin get their class's from ``class_margins_m``."""
    if not folder.is_dir():
        raise DataError(f"{folder}: not a map folder")
    npz = folder / "semantic_map.npz"
    if source in ("auto", "semantic") and npz.is_file():
        from semmap.semantic_map import SemanticMap

        smap = SemanticMap.load(npz)
        return smap.costmap(band), f"{npz} (semantic map, {len(smap.objects)} objects)"
    if source == "semantic":
        raise DataError(f"{npz}: no semantic map in the folder")
    from semmap.export import object_footprints_from_records, read_ros_map

    yaml_path = folder / "map.yaml"
    if not yaml_path.is_file():
        raise DataError(f"{folder}: neither semantic_map.npz nor map.yaml found")
    ros = read_ros_map(yaml_path)
    base = costmap_from_ros_occupancy(ros.occupancy, ros.spec, band)
    objects: list[ObjectFootprint] = []
    obj_path = folder / "objects.json"
    if obj_path.is_file():
        try:
            doc = json.loads(obj_path.read_text(encoding="utf-8"))
            records = doc["objects"] if isinstance(doc, dict) else doc
            objects = object_footprints_from_records(records)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DataError(f"{obj_path}: cannot read objects ({exc})") from exc
    # A plain map file carries no existence threshold: every object it lists is kept out of.
    return (paint_objects(base, objects, band, existence_confirm=0.0, class_margins_m=class_margins_m),
            f"{yaml_path} + {len(objects)} objects")


# --- the picture --------------------------------------------------------------------------

_FREE_BGR = (255, 255, 255)
_UNKNOWN_BGR = (200, 200, 200)
_LETHAL_BGR = (40, 40, 40)
_INFLATED_BGR = (200, 210, 250)
_PATH_BGR = (200, 90, 20)


def draw_plan(planner: Planner, costmap: Costmap, result: PlanResult,
              start_xy_m: tuple[float, float], goal_xy_m: tuple[float, float]) -> NDArray[np.uint8]:
    """A BGR picture, north up: costs, inflation, object footprints, the path, start/goal."""
    spec = costmap.spec
    cs = planner.cspace
    img = np.empty((*spec.shape_rc, 3), np.uint8)
    img[:] = _FREE_BGR
    img[~cs.free] = _INFLATED_BGR
    img[costmap.unknown] = _UNKNOWN_BGR
    img[costmap.lethal] = _LETHAL_BGR
    scale = max(1, int(np.ceil(700 / max(spec.shape_rc))))
    img = cv2.resize(img[::-1], (spec.cols * scale, spec.rows * scale), interpolation=cv2.INTER_NEAREST)

    def px(xy: NDArray[np.floating]) -> NDArray[np.int32]:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        col = (xy[:, 0] - spec.origin_xy_m[0]) / spec.resolution_m * scale
        row = spec.rows * scale - (xy[:, 1] - spec.origin_xy_m[1]) / spec.resolution_m * scale
        return np.round(np.stack([col, row], axis=1)).astype(np.int32)

    for fp in costmap.objects:
        color = (40, 40, 220) if fp.blocks(costmap.band) else (60, 170, 60)
        cv2.polylines(img, [px(fp.polygon_xy_m)], True, color, 2, cv2.LINE_AA)
    if result.ok:
        cv2.polylines(img, [px(result.path_xy_m)], False, _PATH_BGR, max(2, scale), cv2.LINE_AA)
        for p in px(result.path_xy_m):
            cv2.circle(img, (int(p[0]), int(p[1])), max(2, scale), _PATH_BGR, -1, cv2.LINE_AA)
    s, g = px(np.array(start_xy_m))[0], px(np.array(goal_xy_m))[0]
    cv2.circle(img, (int(s[0]), int(s[1])), 4 + scale, (40, 160, 40), -1, cv2.LINE_AA)
    cv2.circle(img, (int(g[0]), int(g[1])), 4 + scale, (40, 40, 200), -1, cv2.LINE_AA)
    if result.goal_xy_m is not None and result.snapped_goal:
        sg = px(np.array(result.goal_xy_m))[0]
        cv2.circle(img, (int(sg[0]), int(sg[1])), 4 + scale, (40, 40, 200), 2, cv2.LINE_AA)
    text = (f"{result.status.value}: {result.length_m:.2f} m, {result.planning_time_s * 1e3:.0f} ms ({result.source})"
            if result.ok else f"{result.status.value}: {result.reason}")
    banner = np.full((26, img.shape[1], 3), 40, np.uint8)
    cv2.putText(banner, text[:120], (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return np.vstack([banner, img])


def _run(args: argparse.Namespace) -> int:
    full_cfg = load_config(args.config)
    cfg: PlannerConfig = full_cfg.planner
    updates: dict[str, object] = {}
    if args.altitude is not None:
        updates["flight_altitude_m"] = args.altitude
    if args.algorithm is not None:
        updates["algorithm"] = args.algorithm
    if args.time_limit is not None:
        updates["time_limit_s"] = args.time_limit
    if updates:
        try:
            cfg = PlannerConfig.model_validate({**cfg.model_dump(), **updates})
        except ValueError as exc:
            raise DataError(f"bad planner option: {exc}") from exc
    planner = Planner(cfg)
    try:
        margins = {c.name: c.margin_m for c in full_cfg.classes}
        costmap, what = load_map(Path(args.map), planner.band, args.source, margins)
    except MapError as exc:
        raise DataError(str(exc)) from exc
    log.info("planning on %s at %.2f m altitude", what, cfg.flight_altitude_m)
    planner.set_map(costmap)
    result = planner.plan(args.start, args.goal, snap_goal=args.snap or None)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(out), draw_plan(planner, costmap, result, args.start, args.goal)):
            raise DataError(f"{out}: cannot write the picture")
    if args.json:
        print(json.dumps(_json_safe({
            "status": result.status.value, "reason": result.reason,
            "path_xy_m": np.round(result.path_xy_m, 4).tolist(), "length_m": result.length_m,
            "cost": result.cost, "planning_time_s": result.planning_time_s,
            "first_solution_time_s": result.first_solution_time_s, "goal_xy_m": result.goal_xy_m,
            "snapped_goal": result.snapped_goal, "source": result.source,
        }), allow_nan=False))
    elif result.ok:
        print(f"path: {len(result.path_xy_m)} points, {result.length_m:.2f} m, cost {result.cost:.2f}, "
              f"first path after {result.first_solution_time_s * 1e3:.1f} ms, total "
              f"{result.planning_time_s * 1e3:.1f} ms ({result.source})")
        for x, y in result.path_xy_m:
            print(f"  {x:8.3f} {y:8.3f}")
    else:
        print(f"no path ({result.status.value}): {result.reason}")
    return 0 if result.ok else 1
