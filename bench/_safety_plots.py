"""Pictures of the safety bench, drawn with OpenCV (no plotting library needed).

* :func:`rates_chart`: collision rate and success per map type (all flights and by kind);
* :func:`clearance_histogram`: each flight's minimum clearance, per map type;
* :func:`example_room`: one room from above with the metric-only and the semantic flight.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.sim.world import Room
from semmap.costmap import VerticalBand

#: BGR colours of the two map types (orange: metric-only, blue: semantic).
COLOURS = {"metric": (0, 140, 255), "semantic": (200, 90, 20)}
LABELS = {"metric": "metric-only map", "semantic": "semantic map"}
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text(img: NDArray[np.uint8], s: str, xy: tuple[int, int], scale: float = 0.5,
          colour: tuple[int, int, int] = (0, 0, 0), thick: int = 1) -> None:
    cv2.putText(img, s, (int(xy[0]), int(xy[1])), FONT, scale, colour, thick, cv2.LINE_AA)


def _write(path: Path, img: NDArray[np.uint8]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write picture")
    return path


def _legend(img: NDArray[np.uint8], x: int, y: int) -> None:
    for i, name in enumerate(("metric", "semantic")):
        yy = y + 20 * i
        cv2.rectangle(img, (x, yy - 10), (x + 14, yy + 2), COLOURS[name], -1)
        _text(img, LABELS[name], (x + 20, yy + 1), 0.45)


def rates_chart(path: Path, groups: Sequence[tuple[str, Mapping[str, Mapping[str, float]]]]) -> Path:
    """Grouped bars, 0-100 %: for each ``(title, {map: {"collision_rate_pct", "success_rate_pct"}})``
    a panel with both rates per map type."""
    panel_w, h, top, bottom = 300, 380, 50, 80
    img = np.full((h, 60 + panel_w * len(groups) + 20, 3), 255, np.uint8)
    plot_h = h - top - bottom
    x0 = 60
    for y_pct in range(0, 101, 25):
        y = top + plot_h - int(plot_h * y_pct / 100)
        cv2.line(img, (x0 - 5, y), (img.shape[1] - 20, y), (225, 225, 225), 1)
        _text(img, f"{y_pct}%", (8, y + 5), 0.45)
    for gi, (title, by_map) in enumerate(groups):
        gx = x0 + gi * panel_w
        _text(img, title, (gx + 10, top - 25), 0.5, thick=1)
        for mi, metric in enumerate(("collision_rate_pct", "success_rate_pct")):
            label = "collisions" if mi == 0 else "success"
            cx = gx + 20 + mi * 135
            for k, name in enumerate(("metric", "semantic")):
                v = float(by_map.get(name, {}).get(metric, 0.0))
                bx = cx + k * 55
                by = top + plot_h - int(round(plot_h * min(max(v, 0.0), 100.0) / 100.0))
                cv2.rectangle(img, (bx, by), (bx + 45, top + plot_h), COLOURS[name], -1)
                _text(img, f"{v:.0f}%", (bx + 4, by - 6), 0.45)
            _text(img, label, (cx + 12, top + plot_h + 20), 0.5)
    cv2.line(img, (x0, top + plot_h), (img.shape[1] - 20, top + plot_h), (0, 0, 0), 1)
    _legend(img, x0, h - 32)
    return _write(path, img)


def clearance_histogram(path: Path, clearances_m: Mapping[str, Sequence[float]], lo_m: float = -0.3,
                        hi_m: float = 0.8, bin_m: float = 0.05) -> Path:
    """Histogram of per-flight minimum clearances (metres, < 0 = collision) per map type; values
    outside ``[lo_m, hi_m]`` go into the end bins."""
    edges = np.arange(lo_m, hi_m + bin_m / 2, bin_m)
    n_bins = len(edges) - 1
    counts = {}
    for name, vals in clearances_m.items():
        v = np.clip(np.asarray([x for x in vals if math.isfinite(x)], dtype=np.float64), lo_m, hi_m - 1e-9)
        counts[name] = np.histogram(v, edges)[0]
    w, h, left, top, bottom = 760, 360, 60, 40, 70
    img = np.full((h, w, 3), 255, np.uint8)
    plot_w, plot_h = w - left - 20, h - top - bottom
    cmax = max(1, max((int(c.max()) for c in counts.values() if len(c)), default=1))
    bw = plot_w / n_bins
    for i in range(n_bins):
        for k, name in enumerate(("metric", "semantic")):
            c = int(counts.get(name, np.zeros(n_bins, int))[i])
            if c == 0:
                continue
            x = int(left + i * bw + k * bw / 2)
            y = top + plot_h - int(round(plot_h * c / cmax))
            cv2.rectangle(img, (x + 1, y), (int(x + bw / 2) - 1, top + plot_h), COLOURS[name], -1)
    cv2.line(img, (left, top + plot_h), (left + plot_w, top + plot_h), (0, 0, 0), 1)
    x_zero = int(left + (0.0 - lo_m) / bin_m * bw)
    cv2.line(img, (x_zero, top - 5), (x_zero, top + plot_h), (0, 0, 220), 1)
    _text(img, "collision", (x_zero - 78, top + 8), 0.45, (0, 0, 220))
    for xv in np.arange(lo_m, hi_m + 1e-9, 0.1):
        x = int(left + (xv - lo_m) / bin_m * bw)
        cv2.line(img, (x, top + plot_h), (x, top + plot_h + 4), (0, 0, 0), 1)
        _text(img, f"{xv:.1f}", (x - 12, top + plot_h + 18), 0.4)
    for c in range(0, cmax + 1, max(1, cmax // 5)):
        y = top + plot_h - int(round(plot_h * c / cmax))
        _text(img, str(c), (20, y + 5), 0.4)
    _text(img, "minimum clearance per flight (m, vehicle side to furniture/walls in its band + margin)",
          (left, h - 35), 0.45)
    _text(img, "flights", (8, top - 15), 0.45)
    _legend(img, w - 200, top)
    return _write(path, img)


def example_room(path: Path, room: Room, band: VerticalBand, slice_band: VerticalBand,
                 paths_room_m: Mapping[str, NDArray[np.floating]], start_xy_m: tuple[float, float],
                 goal_xy_m: tuple[float, float], collisions_room_m: Mapping[str, NDArray[np.floating]],
                 title: str, px_per_m: float = 90.0) -> Path:
    """The room from above: walls, furniture footprints (dark: reaches into the flight band;
    light: below or above it), the parts a depth slice at flight altitude sees (black), both
    flown paths (room frame (N, 2+)) with their collision points (red), start and goal."""
    pad = 0.3
    W = int((room.width_m + 2 * pad) * px_per_m)
    H = int((room.depth_m + 2 * pad) * px_per_m) + 60
    img = np.full((H, W, 3), 255, np.uint8)

    def px(xy: NDArray[np.floating]) -> NDArray[np.int32]:
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.column_stack([(q[:, 0] + pad) * px_per_m,
                                H - 60 - (q[:, 1] + pad) * px_per_m]).round().astype(np.int32)

    for o in room.objects:
        blocks = band.intersects(*o.z_range_m)
        fill = (150, 150, 150) if blocks else (225, 225, 225)
        poly = px(o.footprint_xy_m())
        cv2.fillPoly(img, [poly], fill, cv2.LINE_AA)
        c = poly.mean(axis=0).astype(int)
        _text(img, o.class_name.replace("_", " "), (int(c[0]) - 30, int(c[1]) + 4), 0.38, (60, 60, 60))
    for box, _oid in room.all_boxes():
        if slice_band.intersects(*box.z_range_m):
            cv2.fillPoly(img, [px(box.corners_xy_m())], (0, 0, 0), cv2.LINE_AA)
    for name in ("metric", "semantic"):
        p = paths_room_m.get(name)
        if p is not None and len(p) >= 2:
            cv2.polylines(img, [px(np.asarray(p)[:, :2])], False, COLOURS[name], 3, cv2.LINE_AA)
        hits = collisions_room_m.get(name)
        if hits is not None and len(hits):
            for q in px(np.asarray(hits)[:, :2])[:: max(1, len(hits) // 30)]:
                cv2.circle(img, (int(q[0]), int(q[1])), 4, (0, 0, 230), -1, cv2.LINE_AA)
    for xy, label in ((start_xy_m, "start"), (goal_xy_m, "goal")):
        q = px(np.array(xy))[0]
        cv2.circle(img, (int(q[0]), int(q[1])), 7, (0, 160, 0), 2, cv2.LINE_AA)
        _text(img, label, (int(q[0]) + 9, int(q[1]) - 9), 0.5, (0, 120, 0))
    _text(img, title, (10, H - 36), 0.5)
    _text(img, "dark: furniture in the flight band, black: what the depth slice sees, red: collisions",
          (10, H - 14), 0.42, (60, 60, 60))
    _legend(img, W - 190, H - 40)
    return _write(path, img)
