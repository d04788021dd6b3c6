"""Polygon helpers in the map plane (metres, (N, 2) arrays): convex hull, simplification,
oriented bounding rectangles (and growing one to a least size), area, point-in-convex test,
convex intersection and IoU.

Shared by the object geometry (:mod:`semmap.geometry`), the object map
(:mod:`semmap.objects`) and its footprint evidence (:mod:`semmap.object_evidence`).
Footprints have a handful of vertices, so several of these work on plain floats where numpy's
per-call cost would dominate.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "convex_footprint", "convex_gap_m", "convex_intersection", "convex_iou", "grow_to_least_size", "inside_convex",
    "min_area_rectangle", "min_perimeter_rectangle", "polygon_area_m2", "simplify_polygon",
]


def convex_footprint(xy_m: NDArray[np.floating], min_width_m: float = 0.0) -> NDArray[np.float64]:
    """Counter-clockwise convex hull (M, 2) of (N, 2) points.

    Degenerate inputs (fewer than three points, all on a line: a board seen edge-on) give a
    rectangle around the points at least ``min_width_m`` wide, never a zero-area polygon.
    """
    xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    if len(xy) >= 3:
        # OpenCV's monotone chain is an order of magnitude faster than Qhull on small sets;
        # with clockwise=False it returns counter-clockwise vertices for y-up coordinates.
        origin = _min_xy(xy)
        hull = cv2.convexHull((xy - origin).astype(np.float32), clockwise=False, returnPoints=False)
        poly = xy[np.asarray(hull).reshape(-1)]
        if len(poly) >= 3:
            area = polygon_area_m2(poly)
            if area >= (min_width_m * 0.5) ** 2 and area > 0:
                return poly
    return _thin_rectangle(xy, min_width_m)


def _min_xy(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(2,) per-coordinate minimum of (N, 2) points: two contiguous-ish reductions, where
    ``min(axis=0)`` over (N, 2) (often a view into (N, 3) points) strides at four times the
    cost."""
    return np.array([xy[:, 0].min(), xy[:, 1].min()])


def simplify_polygon(polygon_xy_m: NDArray[np.float64], tolerance_m: float) -> NDArray[np.float64]:
    """Douglas-Peucker simplification of a closed polygon (M, 2) to within ``tolerance_m``
    (fewer vertices make every later overlap test cheaper). Keeps at least a triangle."""
    if len(polygon_xy_m) <= 4:
        return polygon_xy_m
    origin = _min_xy(polygon_xy_m)
    idx = cv2.approxPolyDP((polygon_xy_m - origin).astype(np.float32).reshape(-1, 1, 2),
                           float(tolerance_m), True)
    out = np.asarray(idx, dtype=np.float64).reshape(-1, 2) + origin
    return out if len(out) >= 3 and polygon_area_m2(out) > 0 else polygon_xy_m


def _thin_rectangle(xy: NDArray[np.float64], min_width_m: float) -> NDArray[np.float64]:
    """Oriented rectangle along the principal axis of (N, 2) points, each side at least
    ``min_width_m`` long."""
    if len(xy) == 0:
        raise ValueError("no points to build a footprint from")
    c = xy.mean(axis=0)
    d = xy - c
    if len(xy) >= 2 and np.ptp(d, axis=0).max() > 0:
        _, _, vt = np.linalg.svd(d, full_matrices=False)
        axis = vt[0]
    else:
        axis = np.array([1.0, 0.0])
    perp = np.array([-axis[1], axis[0]])
    a, b = d @ axis, d @ perp
    half = min_width_m / 2.0
    a0, a1 = min(a.min(), -half), max(a.max(), half)
    b0, b1 = min(b.min(), -half), max(b.max(), half)
    corners = np.array([[a0, b0], [a1, b0], [a1, b1], [a0, b1]])
    return c + corners[:, :1] * axis + corners[:, 1:] * perp


def _caliper_rectangle(xy_m: NDArray[np.floating], by: Literal["area", "perimeter"]) -> NDArray[np.float64]:
    """The oriented rectangle (4, 2), counter-clockwise, around points or a polygon (N, 2) that
    minimises its area or its perimeter.

    Rotating calipers on the convex hull: either optimum has a side along a hull edge, so every
    edge direction is tried at once (vectorised). For the perimeter, ties go to the smaller area.
    """
    hull = convex_footprint(xy_m)
    edges = np.roll(hull, -1, axis=0) - hull
    lengths = np.linalg.norm(edges, axis=1)
    edges = edges[lengths > 1e-12] / lengths[lengths > 1e-12, None]  # (E, 2) unit directions
    if len(edges) == 0:
        return hull
    perp = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
    a = hull @ edges.T  # (M, E)
    b = hull @ perp.T
    ext_a, ext_b = a.max(0) - a.min(0), b.max(0) - b.min(0)
    if by == "area":
        k = int(np.argmin(ext_a * ext_b))
    else:
        # Perimeter first; the area term (metres^2, scaled far below a millimetre) breaks ties.
        k = int(np.argmin(ext_a + ext_b + 1e-6 * ext_a * ext_b))
    a0, a1, b0, b1 = a[:, k].min(), a[:, k].max(), b[:, k].min(), b[:, k].max()
    corners = np.array([[a0, b0], [a1, b0], [a1, b1], [a0, b1]])
    return corners[:, :1] * edges[k] + corners[:, 1:] * perp[k]


def min_area_rectangle(polygon_xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """Smallest-area oriented rectangle (4, 2), counter-clockwise, enclosing a polygon (M, 2)."""
    return _caliper_rectangle(polygon_xy_m, "area")


def min_perimeter_rectangle(xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """Least-perimeter oriented rectangle (4, 2), counter-clockwise, around points (N, 2); ties
    go to the smaller area. Unlike the least-area one it is unambiguous for an L or a right
    triangle of points (why the object map's footprints use it: see
    :mod:`semmap.object_evidence`)."""
    return _caliper_rectangle(xy_m, "perimeter")


def rectangle_along(xy_m: NDArray[np.floating], direction_rad: float) -> NDArray[np.float64]:
    """The rectangle (4, 2), counter-clockwise, around points (N, 2) whose sides run along
    ``direction_rad`` and across it."""
    axis = np.array([math.cos(direction_rad), math.sin(direction_rad)])
    perp = np.array([-axis[1], axis[0]])
    pts = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    a, b = pts @ axis, pts @ perp
    corners = np.array([[a.min(), b.min()], [a.max(), b.min()], [a.max(), b.max()], [a.min(), b.max()]])
    return corners[:, :1] * axis + corners[:, 1:] * perp


def grow_to_least_size(
    polygon_xy_m: NDArray[np.floating], least_size_m: tuple[float, float],
    away_from_xy: NDArray[np.floating] | tuple[float, float] = (0.0, 0.0),
) -> NDArray[np.float64]:
    """The polygon's least-perimeter rectangle grown until its long side is at least
    ``least_size_m[0]`` and its short side at least ``least_size_m[1]`` (4, 2), or the polygon
    itself (as float64) when it is that large already.

    ``away_from_xy`` says where the growth goes: the mean unit vector from the viewpoints to
    the object (length 0..1). Along each side's axis the missing length is split in proportion
    to how much that axis points away from the viewers, so a part seen from one side grows on
    its unseen side, and one seen from all round (or with no direction) grows evenly.
    """
    poly = np.asarray(polygon_xy_m, dtype=np.float64).reshape(-1, 2)
    least_long, least_short = max(least_size_m), min(least_size_m)
    rect = min_perimeter_rectangle(poly)
    e0, e1 = rect[1] - rect[0], rect[3] - rect[0]
    n0, n1 = float(np.hypot(*e0)), float(np.hypot(*e1))
    if n0 < 1e-9 or n1 < 1e-9:
        return poly
    if n0 < n1:  # axis 0 is the long side
        e0, e1, n0, n1 = e1, e0, n1, n0
    grow = (max(0.0, least_long - n0), max(0.0, least_short - n1))
    if grow == (0.0, 0.0):
        return poly
    away = np.asarray(away_from_xy, dtype=np.float64).reshape(2)
    u, v = e0 / n0, e1 / n1
    lo, hi = [], []
    for axis, length, g in ((u, n0, grow[0]), (v, n1, grow[1])):
        c = float(np.clip(away @ axis, -1.0, 1.0))  # +1: the viewers look along +axis
        lo.append(-g * (1.0 - c) / 2.0)
        hi.append(length + g * (1.0 + c) / 2.0)
    corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
    out = np.array([rect[0] + a * u + b * v for a, b in corners])
    return out if _signed_area(out.tolist()) > 0 else out[::-1].copy()


def inside_convex(poly: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) True where points (N, 2) lie inside a convex polygon (M, 2), either winding."""
    e = np.roll(poly, -1, axis=0) - poly  # (M, 2)
    cross = e[None, :, 0] * (xy[:, None, 1] - poly[None, :, 1]) - e[None, :, 1] * (xy[:, None, 0] - poly[None, :, 0])
    return np.all(cross >= -1e-12, axis=1) | np.all(cross <= 1e-12, axis=1)


def _signed_area(pts: list[list[float]]) -> float:
    """Shoelace signed area (counter-clockwise positive) of a vertex list, in plain floats:
    footprints have a handful of vertices, where numpy's per-call cost dominates."""
    n = len(pts)
    acc = 0.0
    for i in range(n):
        x0, y0 = pts[i]
        x1, y1 = pts[(i + 1) % n]
        acc += x0 * y1 - x1 * y0
    return 0.5 * acc


def polygon_area_m2(polygon_xy_m: NDArray[np.floating]) -> float:
    """Area of a simple polygon (M, 2) by the shoelace formula, any winding."""
    p = np.asarray(polygon_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(p) < 3:
        return 0.0
    return abs(_signed_area(p.tolist()))


def _ccw(poly: NDArray[np.float64]) -> NDArray[np.float64]:
    return poly if _signed_area(poly.tolist()) >= 0 else poly[::-1]


def convex_intersection(
    a_xy_m: NDArray[np.floating], b_xy_m: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Intersection (K, 2) of two convex polygons (M, 2), (L, 2) by Sutherland-Hodgman
    clipping; empty (0, 2) when they do not overlap."""
    a = np.asarray(a_xy_m, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(a) < 3 or len(b) < 3:
        return np.zeros((0, 2))
    if (a.max(axis=0) < b.min(axis=0)).any() or (b.max(axis=0) < a.min(axis=0)).any():
        return np.zeros((0, 2))
    return _clip_convex(np.ascontiguousarray(_ccw(a)), np.ascontiguousarray(_ccw(b)))


@numba.njit(cache=True)
def _clip_convex(subject: NDArray[np.float64], clip: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sutherland-Hodgman: ``subject`` (M, 2) clipped by each edge of the counter-clockwise
    convex ``clip`` (L, 2) in turn (compiled: the object map runs it for every pair of nearby
    footprints each frame)."""
    out = subject.copy()
    n_clip = clip.shape[0]
    for i in range(n_clip):
        n = out.shape[0]
        if n == 0:
            break
        px, py = clip[i, 0], clip[i, 1]
        ex, ey = clip[(i + 1) % n_clip, 0] - px, clip[(i + 1) % n_clip, 1] - py
        nxt = np.empty((2 * n, 2), np.float64)  # each vertex adds itself and a crossing at most
        k = 0
        for j in range(n):
            x0, y0 = out[j, 0], out[j, 1]
            x1, y1 = out[(j + 1) % n, 0], out[(j + 1) % n, 1]
            # Left of the directed edge (inside a counter-clockwise clip polygon) is >= 0.
            s0 = ex * (y0 - py) - ey * (x0 - px)
            s1 = ex * (y1 - py) - ey * (x1 - px)
            if s0 >= 0:
                nxt[k, 0], nxt[k, 1] = x0, y0
                k += 1
            if (s0 >= 0) != (s1 >= 0):
                t = s0 / (s0 - s1)
                nxt[k, 0], nxt[k, 1] = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
                k += 1
        out = nxt[:k].copy()
    return out


def convex_iou(a_xy_m: NDArray[np.floating], b_xy_m: NDArray[np.floating]) -> float:
    """Intersection over union of two convex polygons (M, 2), (L, 2); 0 when disjoint."""
    inter = polygon_area_m2(convex_intersection(a_xy_m, b_xy_m))
    if inter <= 0.0:
        return 0.0
    union = polygon_area_m2(a_xy_m) + polygon_area_m2(b_xy_m) - inter
    return inter / union if union > 0 else 0.0


def _point_segment_distance_m(p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, M) distance from each point (N, 2) to each segment a[j]-b[j] (M, 2)."""
    ab = b - a  # (M, 2)
    ap = p[:, None, :] - a[None, :, :]  # (N, M, 2)
    t = np.clip((ap * ab[None]).sum(axis=2) / np.maximum((ab * ab).sum(axis=1), 1e-18)[None], 0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return np.hypot(d[..., 0], d[..., 1])


def convex_gap_m(a_xy_m: NDArray[np.floating], b_xy_m: NDArray[np.floating]) -> float:
    """Distance between two convex polygons (M, 2), (L, 2): 0 when they overlap, else the least
    vertex-to-edge distance (exact for disjoint convex polygons)."""
    a = np.asarray(a_xy_m, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(a) < 3 or len(b) < 3:
        raise ValueError(f"convex_gap_m needs two polygons of 3+ vertices, got {len(a)} and {len(b)}")
    if inside_convex(a, b).any() or inside_convex(b, a).any() or len(convex_intersection(a, b)) >= 3:
        return 0.0
    ea, eb = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    return float(min(_point_segment_distance_m(a, b, eb).min(), _point_segment_distance_m(b, a, ea).min()))
