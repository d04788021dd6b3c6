"""Exports of the semantic map: ROS map_server PGM + YAML, nav_msgs values, a PNG picture,
``objects.json`` and GeoJSON.

ROS conventions (``map_server`` / nav2 ``map_io``): the PGM's first row is the *top* of the
map (largest y), ``origin`` is the map-frame pose ``[x, y, yaw]`` of the lower-left pixel, and
with ``negate: 0`` a pixel ``p`` means occupancy ``(255 - p) / 255``. ``trinary`` files use
0 = occupied, 254 = free, 205 = unknown like ``map_saver``; ``scale`` files keep the
probability (still 205 for unknown). nav_msgs/OccupancyGrid data is row-major from the
lower-left cell, 0..100 percent and -1 unknown: exactly our grid's row order.

Every writer goes through a temp file and rename, so a reader never sees half a file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from semmap.costmap import (
    INSCRIBED_INFLATED_OBSTACLE,
    MAX_NON_OBSTACLE,
    NO_INFORMATION,
    ObjectFootprint,
)
from semmap.errors import MapError
from semmap.grid import Bounds, GridSpec
from semmap.semantic_map import SemanticMap, atomic_write_bytes

#: PGM values map_saver writes in trinary mode.
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
#: WGS-84 equatorial radius (the same flat-earth model as PX4's local projection).
EARTH_RADIUS_M = 6_378_137.0


# --- ROS map_server ------------------------------------------------------------------------

def probability_to_pgm(
    probability: NDArray[np.floating], mode: str = "trinary",
    occupied_above: float = 0.5, free_below: float = 0.5,
) -> NDArray[np.uint8]:
    """(rows, cols) probabilities (NaN = unknown, row 0 = south) -> (rows, cols) uint8 PGM
    image with row 0 = north, for ``negate: 0``.

    ``trinary``: cells above ``occupied_above`` are occupied, below ``free_below`` free (a
    Cartographer grid with hit 0.55 / miss 0.49 needs many misses to go far below 0.5, so
    the side of 0.5 is the belief), the rest unknown. ``scale``: ``255 - 255 p``.
    """
    p = np.asarray(probability, np.float64)
    known = np.isfinite(p)
    if mode == "trinary":
        img = np.full(p.shape, PGM_UNKNOWN, np.uint8)
        img[known & (p > occupied_above)] = PGM_OCCUPIED
        img[known & (p < free_below)] = PGM_FREE
    elif mode == "scale":
        img = np.full(p.shape, PGM_UNKNOWN, np.uint8)
        img[known] = np.rint(255.0 - np.clip(p[known], 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        raise MapError(f"unknown map mode {mode!r} (use 'trinary' or 'scale')")
    return img[::-1].copy()


def encode_pgm(image: NDArray[np.uint8]) -> bytes:
    """Binary (P5) PGM with maxval 255 of a (rows, cols) uint8 image."""
    img = np.ascontiguousarray(image, np.uint8)
    if img.ndim != 2:
        raise MapError(f"PGM image must be 2-D, got shape {img.shape}")
    header = f"P5\n# semantic-companion map\n{img.shape[1]} {img.shape[0]}\n255\n".encode("ascii")
    return header + img.tobytes()


def write_ros_map(
    stem: str | Path, probability: NDArray[np.floating], spec: GridSpec, mode: str = "trinary",
    occupied_above: float = 0.5, free_below: float = 0.5,
    occupied_thresh: float = 0.65, free_thresh: float = 0.196,
) -> tuple[Path, Path]:
    """Write ``<stem>.pgm`` and ``<stem>.yaml`` loadable by ``map_server`` / nav2.

    ``probability``: (rows, cols) occupancy 0..1 in grid order, NaN where unknown.
    ``occupied_above``/``free_below`` classify cells when writing (see
    :func:`probability_to_pgm`); ``occupied_thresh``/``free_thresh`` go into the YAML for the
    reader and keep map_saver's values, which read 0/254/205 back as occupied/free/unknown.
    Returns the two paths.
    """
    stem = Path(stem)
    p = np.asarray(probability)
    if p.shape != spec.shape_rc:
        raise MapError(f"probability shape {p.shape} does not match the grid {spec.shape_rc}")
    pgm_path, yaml_path = stem.with_suffix(".pgm"), stem.with_suffix(".yaml")
    atomic_write_bytes(pgm_path, encode_pgm(probability_to_pgm(p, mode, occupied_above, free_below)))
    meta = {
        "image": pgm_path.name,
        "mode": mode,
        "resolution": float(spec.resolution_m),
        "origin": [float(spec.origin_xy_m[0]), float(spec.origin_xy_m[1]), 0.0],
        "negate": 0,
        "occupied_thresh": float(occupied_thresh),
        "free_thresh": float(free_thresh),
    }
    atomic_write_bytes(yaml_path, yaml.safe_dump(meta, sort_keys=False).encode("utf-8"))
    return pgm_path, yaml_path


@dataclass(frozen=True, eq=False)
class RosMap:
    """A map read back from PGM + YAML: ``occupancy`` (rows, cols) int8 nav_msgs values in
    grid order (row 0 = south), the raw ``image`` (row 0 = north) and the YAML fields."""

    spec: GridSpec
    occupancy: NDArray[np.int8]
    image: NDArray[np.uint8]
    meta: dict[str, Any]


def read_ros_map(yaml_path: str | Path) -> RosMap:
    """Load a map_server map the way nav2's ``map_io`` interprets it."""
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise MapError(f"{yaml_path}: cannot read map YAML ({exc})") from exc
    if not isinstance(meta, dict):
        raise MapError(f"{yaml_path}: map YAML must be a mapping")
    for key in ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"):
        if key not in meta:
            raise MapError(f"{yaml_path}: missing key {key!r}")
    image_path = yaml_path.parent / str(meta["image"])
    img = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise MapError(f"{image_path}: cannot read map image")
    mode = meta.get("mode", "trinary")
    occ = (255.0 - img) / 255.0 if not meta["negate"] else img / 255.0
    out = np.full(img.shape, -1, np.int8)
    hi, lo = float(meta["occupied_thresh"]), float(meta["free_thresh"])
    out[occ > hi] = 100
    out[occ < lo] = 0
    if mode == "scale":
        mid = (occ <= hi) & (occ >= lo) & (img != PGM_UNKNOWN)
        out[mid] = np.rint(99.0 * (occ[mid] - lo) / (hi - lo)).astype(np.int8)
    elif mode != "trinary":
        raise MapError(f"{yaml_path}: mode {mode!r} not supported (trinary, scale)")
    res = float(meta["resolution"])
    spec = GridSpec(res, (float(meta["origin"][0]), float(meta["origin"][1])), img.shape)
    return RosMap(spec, out[::-1].copy(), np.asarray(img, np.uint8), meta)


def nav_msgs_values(probability: NDArray[np.floating]) -> NDArray[np.int8]:
    """(rows, cols) probabilities (NaN unknown) -> int8 0..100 percent, -1 unknown, in
    nav_msgs/OccupancyGrid order (row-major from the lower-left cell; flatten for ``data``)."""
    p = np.asarray(probability, np.float64)
    out = np.full(p.shape, -1, np.int8)
    known = np.isfinite(p)
    out[known] = np.rint(np.clip(p[known], 0.0, 1.0) * 100.0).astype(np.int8)
    return out


def cost_to_probability(cost: NDArray[np.uint8]) -> NDArray[np.float32]:
    """Costmap costs -> pseudo-probabilities for map exports: inscribed/lethal 1, soft costs
    scaled to [0, 1), NO_INFORMATION NaN."""
    c = np.asarray(cost)
    p = np.minimum(c.astype(np.float32) / MAX_NON_OBSTACLE, 0.99).astype(np.float32)
    p[c >= INSCRIBED_INFLATED_OBSTACLE] = 1.0
    p[c == NO_INFORMATION] = np.nan
    return p


# --- objects --------------------------------------------------------------------------------

def object_records(smap: SemanticMap) -> list[dict[str, Any]]:
    """One JSON-ready dict per object (map frame, metres)."""
    out = []
    for fp in smap.objects:
        poly = np.asarray(fp.polygon_xy_m, np.float64).reshape(-1, 2)
        probs = smap.class_probabilities(fp.object_id)
        out.append({
            "object_id": int(fp.object_id),
            "class_name": fp.class_name,
            "class_probabilities": {n: round(float(p), 4) for n, p in zip(smap.class_names, probs, strict=True)},
            "existence": round(float(fp.existence), 4),
            "centroid_xy_m": [round(float(v), 4) for v in poly.mean(axis=0)],
            "polygon_xy_m": [[round(float(x), 4), round(float(y), 4)] for x, y in poly],
            "z_min_m": round(float(fp.z_min_m), 4),
            "z_max_m": round(float(fp.z_max_m), 4),
            "height_m": round(float(fp.z_max_m), 4),
            "margin_m": round(fp.resolved_margin_m, 4),
        })
    return out


def write_objects_json(path: str | Path, smap: SemanticMap) -> Path:
    """``objects.json``: the object list with the frame and units stated."""
    doc = {
        "frame": "map (x east, y north, z up; metres above the floor)",
        "class_names": list(smap.class_names),
        "objects": object_records(smap),
    }
    path = Path(path)
    atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode("utf-8"))
    return path


def map_to_lon_lat(
    xy_m: NDArray[np.floating], origin_lat_deg: float, origin_lon_deg: float,
) -> NDArray[np.float64]:
    """(N, 2) map-frame (east, north) metres -> (N, 2) (lon, lat) degrees around a geographic
    origin (the map origin), equirectangular approximation (mm-accurate over a building)."""
    xy = np.asarray(xy_m, np.float64).reshape(-1, 2)
    lat = origin_lat_deg + np.degrees(xy[:, 1] / EARTH_RADIUS_M)
    lon = origin_lon_deg + np.degrees(xy[:, 0] / (EARTH_RADIUS_M * math.cos(math.radians(origin_lat_deg))))
    return np.stack([lon, lat], axis=1)


def geojson(smap: SemanticMap, origin_lat_deg: float, origin_lon_deg: float) -> dict[str, Any]:
    """A GeoJSON FeatureCollection (RFC 7946: lon, lat order, closed rings) of the objects'
    footprints and the vehicle path."""
    features: list[dict[str, Any]] = []
    for rec, fp in zip(object_records(smap), smap.objects, strict=True):
        ring = map_to_lon_lat(np.asarray(fp.polygon_xy_m), origin_lat_deg, origin_lon_deg)
        ring = np.concatenate([ring, ring[:1]])
        props = {k: v for k, v in rec.items() if k not in ("polygon_xy_m",)}
        features.append({
            "type": "Feature",
            "geometry": {"type": "Polygon", "coordinates": [ring.round(9).tolist()]},
            "properties": props,
        })
    path = smap.path_xyz_m
    if len(path) >= 2:
        line = map_to_lon_lat(path[:, :2], origin_lat_deg, origin_lon_deg)
        features.append({
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": line.round(9).tolist()},
            "properties": {"kind": "vehicle_path"},
        })
    return {"type": "FeatureCollection", "features": features}


def write_geojson(path: str | Path, smap: SemanticMap, origin_lat_deg: float, origin_lon_deg: float) -> Path:
    """Write :func:`geojson` to ``path``."""
    path = Path(path)
    doc = geojson(smap, origin_lat_deg, origin_lon_deg)
    atomic_write_bytes(path, (json.dumps(doc) + "\n").encode("utf-8"))
    return path


# --- the picture ------------------------------------------------------------------------------

def _grey_image(probability: NDArray[np.floating]) -> NDArray[np.uint8]:
    """(rows, cols, 3) BGR grey, north up: free (p < 0.5) near white, occupied (p > 0.5)
    dark, darker the surer; unknown mid grey. The two halves are stretched separately so a
    cell seen free a few times does not look unknown."""
    p = np.asarray(probability, np.float64)
    grey = np.full(p.shape, 170, np.uint8)
    known = np.isfinite(p)
    pk = np.clip(p[known], 0.0, 1.0)
    free_shade = 255.0 - 35.0 * np.clip((pk - 0.25) / 0.25, 0.0, 1.0)
    occ_shade = 110.0 * (1.0 - np.clip((pk - 0.5) / 0.4, 0.0, 1.0))
    grey[known] = np.rint(np.where(pk < 0.5, free_shade, occ_shade)).astype(np.uint8)
    return np.asarray(cv2.cvtColor(grey[::-1], cv2.COLOR_GRAY2BGR), np.uint8)


def _crop_window(smap: SemanticMap, crop_margin_m: float) -> Bounds:
    """The grid cells to draw: the observed cells plus ``crop_margin_m``, grown to hold every
    object and the path (the whole grid when nothing is observed)."""
    spec = smap.spec
    rows_any, cols_any = np.nonzero(smap.grid.known)
    if len(rows_any):
        window = Bounds(int(rows_any.min()), int(cols_any.min()), int(rows_any.max()) + 1, int(cols_any.max()) + 1)
        window = window.grown(int(math.ceil(crop_margin_m / spec.resolution_m)))
    else:
        window = spec.bounds
    keep = [np.asarray(fp.polygon_xy_m).reshape(-1, 2) for fp in smap.objects]
    if len(smap.path_xyz_m):
        keep.append(smap.path_xyz_m[:, :2])
    for pts_xy in keep:  # never crop an object or the path away
        rc = np.clip(spec.cell_of(pts_xy), 0, [spec.rows - 1, spec.cols - 1])
        lo, hi = rc.min(axis=0), rc.max(axis=0)
        window = window.union(Bounds(int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1).grown(2))
    return window.clipped(spec.shape_rc)


def render_picture(
    smap: SemanticMap, class_colors_rgb: Mapping[str, Sequence[int]] | None = None,
    min_width_px: int = 900, crop_margin_m: float = 0.5,
) -> NDArray[np.uint8]:
    """(H, W, 3) BGR picture: the grid in grey, object footprints filled and outlined in
    their class colour with "class #id existence" labels, the vehicle path, a scale bar.

    Cropped to the observed area (plus ``crop_margin_m``) and upscaled to ``min_width_px``.
    """
    spec = smap.spec
    prob = smap.grid.probability()
    window = _crop_window(smap, crop_margin_m)
    r0, r1, c0, c1 = window.r0, window.r1, window.c0, window.c1
    scale = max(1, int(math.ceil(min_width_px / max(1, c1 - c0))))
    img = _grey_image(prob[r0:r1, c0:c1])
    img = np.asarray(cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST), np.uint8)
    H = img.shape[0]
    res = spec.resolution_m
    x_left = spec.origin_xy_m[0] + c0 * res
    y_top = spec.origin_xy_m[1] + r1 * res

    def to_px(xy: NDArray[np.floating]) -> NDArray[np.int32]:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        u = (xy[:, 0] - x_left) / res * scale
        v = (y_top - xy[:, 1]) / res * scale
        return np.rint(np.stack([u, v], axis=1)).astype(np.int32)

    colors = class_colors_rgb or {}
    overlay = img.copy()
    labels = []
    for fp in smap.objects:
        rgb = colors.get(fp.class_name, _fallback_color(fp.class_name))
        bgr = (int(rgb[2]), int(rgb[1]), int(rgb[0]))
        pts = to_px(fp.polygon_xy_m)
        cv2.fillPoly(overlay, [pts], bgr, cv2.LINE_AA)
        labels.append((pts, bgr, f"{fp.class_name} #{fp.object_id} {fp.existence:.2f}"))
    img = np.asarray(cv2.addWeighted(overlay, 0.35, img, 0.65, 0.0), np.uint8)
    for pts, bgr, _ in labels:
        cv2.polylines(img, [pts], True, bgr, 2, cv2.LINE_AA)
    path = smap.path_xyz_m
    if len(path) >= 2:
        cv2.polylines(img, [to_px(path[:, :2])], False, (200, 90, 0), 2, cv2.LINE_AA)
    if len(path):
        start, end = to_px(path[:1, :2])[0], to_px(path[-1:, :2])[0]
        cv2.circle(img, (int(start[0]), int(start[1])), 6, (0, 160, 0), -1, cv2.LINE_AA)
        cv2.circle(img, (int(end[0]), int(end[1])), 6, (0, 0, 200), -1, cv2.LINE_AA)
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    for pts, _bgr, text in labels:
        (tw, th), _ = cv2.getTextSize(text, font, fs, 1)
        cx, cy = pts.mean(axis=0)
        org = (int(np.clip(cx - tw / 2, 2, img.shape[1] - tw - 2)), int(np.clip(cy + th / 2, th + 2, H - 2)))
        cv2.rectangle(img, (org[0] - 2, org[1] - th - 3), (org[0] + tw + 2, org[1] + 4), (255, 255, 255), -1)
        cv2.putText(img, text, org, font, fs, (0, 0, 0), 1, cv2.LINE_AA)
    _draw_scale_bar(img, res, scale)
    return img


def _draw_scale_bar(img: NDArray[np.uint8], resolution_m: float, scale: int) -> None:
    """A 1 m bar (or 5 m on large maps) in the lower-left corner."""
    px_per_m = scale / resolution_m
    length_m = 1.0 if img.shape[1] / px_per_m < 30 else 5.0
    L = int(round(length_m * px_per_m))
    x0, y0 = 12, img.shape[0] - 14
    cv2.rectangle(img, (x0 - 4, y0 - 20), (x0 + L + 48, y0 + 8), (255, 255, 255), -1)
    cv2.line(img, (x0, y0), (x0 + L, y0), (0, 0, 0), 3)
    cv2.putText(img, f"{length_m:g} m", (x0 + L + 6, y0 + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)


def _fallback_color(name: str) -> tuple[int, int, int]:
    """A stable colour for a class without a configured one."""
    h = sum((i + 1) * ord(c) for i, c in enumerate(name))
    return (80 + h * 37 % 160, 80 + h * 59 % 160, 80 + h * 83 % 160)


def write_picture(
    path: str | Path, smap: SemanticMap, class_colors_rgb: Mapping[str, Sequence[int]] | None = None,
) -> Path:
    """Write :func:`render_picture` as a PNG."""
    path = Path(path)
    ok, buf = cv2.imencode(".png", render_picture(smap, class_colors_rgb))
    if not ok:
        raise MapError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())
    return path


def export_all(
    out_dir: str | Path, smap: SemanticMap, class_colors_rgb: Mapping[str, Sequence[int]] | None = None,
    geo_origin_lat_lon_deg: tuple[float, float] | None = None, altitude_m: float | None = None,
) -> dict[str, Path]:
    """Every export into ``out_dir``: ``map.pgm/.yaml`` (occupancy), ``costmap.pgm/.yaml``
    (the combined costmap of the scan band, or the band at ``altitude_m`` if given, in
    ``scale`` mode), ``map.png``, ``objects.json``, ``objects.geojson`` (with a geographic
    origin) and ``semantic_map.npz`` (the whole map, reloadable)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    files["map_pgm"], files["map_yaml"] = write_ros_map(out / "map", smap.grid.probability(), smap.spec)
    band = smap.settings.scan_band
    if altitude_m is not None:
        half = 0.5 * (band.z_max_m - band.z_min_m)
        band = type(band)(altitude_m - half, altitude_m + half)
    cm = smap.costmap(band)
    files["costmap_pgm"], files["costmap_yaml"] = write_ros_map(
        out / "costmap", cost_to_probability(cm.cost), cm.spec, mode="scale"
    )
    files["picture"] = write_picture(out / "map.png", smap, class_colors_rgb)
    files["objects"] = write_objects_json(out / "objects.json", smap)
    if geo_origin_lat_lon_deg is not None:
        files["geojson"] = write_geojson(out / "objects.geojson", smap, *geo_origin_lat_lon_deg)
    files["map"] = smap.save(out / "semantic_map.npz")
    return files


def object_footprints_from_records(records: Sequence[Mapping[str, Any]]) -> list[ObjectFootprint]:
    """Inverse of :func:`object_records` (for tools that read ``objects.json``)."""
    return [
        ObjectFootprint(
            object_id=int(r["object_id"]), class_name=str(r["class_name"]),
            polygon_xy_m=np.asarray(r["polygon_xy_m"], np.float64).reshape(-1, 2),
            z_min_m=float(r["z_min_m"]), z_max_m=float(r["z_max_m"]),
            existence=float(r["existence"]),
            margin_m=None if r.get("margin_m") is None else float(r["margin_m"]),
        )
        for r in records
    ]
