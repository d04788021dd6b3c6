"""Plane fitting by RANSAC (vectorised), floor estimation and the gravity-aligned map frame.

A plane is ``normal . p + offset_m = 0`` with a unit ``normal``; for horizontal planes the
normal points up, so ``normal . p + offset_m`` is the signed height of ``p`` above the plane.
RANSAC evaluates all its hypotheses at once as one (N, H) distance matrix: a few hundred
hypotheses on a thousand points is a single numpy expression, no Python loop per hypothesis.
With an ``up`` direction the hypotheses are constrained near horizontal (tilt at most
``max_tilt_rad``), and the best exactly-horizontal plane (every point's height tried, by a
window count on sorted heights) joins them, so a seat or table top wins even when most points
lie on vertical surfaces (backrests, legs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.errors import MapError
from semmap.frames import Transform, invert, make_transform

#: Upper bound on the size of one (N, H) distance block, to bound memory.
_MAX_BLOCK = 2_000_000
#: Points on which hypotheses are scored.
_SCORE_POINTS = 256
#: Column orders for a cross product: (a x b) = a[YZX] * b[ZXY] - a[ZXY] * b[YZX].
_YZX = np.array([1, 2, 0])
_ZXY = np.array([2, 0, 1])


@dataclass(frozen=True)
class Plane:
    """``normal . p + offset_m = 0``; ``normal`` (3,) unit length, in the points' frame."""

    normal: tuple[float, float, float]
    offset_m: float

    @property
    def normal_array(self) -> NDArray[np.float64]:
        return np.asarray(self.normal, dtype=np.float64)

    def signed_distance_m(self, points_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N,) signed distance of (N, 3) points along the normal (height above a floor)."""
        return np.asarray(points_m, dtype=np.float64) @ self.normal_array + self.offset_m

    def tilt_rad(self, up: NDArray[np.floating]) -> float:
        """Angle between the normal and the unit vector ``up`` (3,)."""
        u = np.asarray(up, dtype=np.float64)
        c = abs(float(self.normal_array @ u)) / float(np.linalg.norm(u))
        return math.acos(min(1.0, c))

    @classmethod
    def horizontal(cls, height_m: float = 0.0) -> "Plane":
        """The plane z = ``height_m`` with its normal along +z."""
        return cls((0.0, 0.0, 1.0), -float(height_m))


@dataclass(frozen=True, eq=False)
class PlaneFit:
    """A RANSAC result: the refined plane and which input points are its inliers."""

    plane: Plane
    inliers: NDArray[np.bool_]  # (N,)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _refine(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Least-squares plane (normal (3,), offset) through (K, 3) points (K >= 3)."""
    c = points.mean(axis=0)
    d = points - c
    # Smallest-eigenvalue eigenvector of the 3x3 scatter: the same normal as an SVD of the
    # (K, 3) residuals at a fraction of the cost.
    _, vecs = np.linalg.eigh(d.T @ d)
    n = vecs[:, 0]
    return n, -float(n @ c)


def fit_plane(
    points_m: NDArray[np.floating],
    distance_m: float,
    iterations: int,
    rng: np.random.Generator | None = None,
    up: NDArray[np.floating] | None = None,
    max_tilt_rad: float = math.pi / 2,
    min_inliers: int = 3,
) -> PlaneFit | None:
    """Best plane of (N, 3) points: the hypothesis with most points within ``distance_m``.

    ``iterations`` three-point hypotheses are drawn (plus the best exactly-horizontal plane when
    ``up`` (3,) is given); with ``up`` only planes tilted at most ``max_tilt_rad`` from
    horizontal are accepted and the normal is oriented towards ``up``. The winner is refined by
    least squares on its inliers. Returns None when fewer than ``min_inliers`` points support
    any acceptable plane.
    """
    P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    n_pts = len(P)
    if n_pts < 3 or iterations < 1:
        return None
    rng = rng if rng is not None else np.random.default_rng(0)
    idx = rng.integers(0, n_pts, size=(iterations, 3))
    tri = P.take(idx, axis=0)  # (H, 3 points, 3)
    p0 = tri[:, 0]
    a, b = tri[:, 1] - p0, tri[:, 2] - p0
    # a x b without np.cross's axis juggling (its per-call cost exceeds the arithmetic here).
    normals = a[:, _YZX] * b[:, _ZXY] - a[:, _ZXY] * b[:, _YZX]  # (H, 3)
    norms = np.sqrt(np.einsum("hj,hj->h", normals, normals))
    # Rejected hypotheses stay in place, masked out of the vote (cheaper than compacting
    # every array; the winner is the same first maximum).
    valid = norms > 1e-12
    normals /= np.where(valid, norms, 1.0)[:, None]
    u: NDArray[np.float64] | None = None
    if up is not None:
        u = np.asarray(up, dtype=np.float64)
        u = u / np.linalg.norm(u)
        dots = normals @ u
        normals *= np.where(dots < 0, -1.0, 1.0)[:, None]
        valid &= np.abs(dots) >= math.cos(max_tilt_rad) - 1e-12
        # The best exactly-horizontal plane, found exhaustively: every point's height is a
        # hypothesis and its support is a window count on the sorted heights.
        hs = np.sort(P @ u)
        support = np.searchsorted(hs, hs + distance_m, "right") - np.searchsorted(hs, hs - distance_m, "left")
        h_best = float(hs[int(np.argmax(support))])
        normals = np.concatenate([normals, u[None, :]])
        p0 = np.concatenate([p0, (h_best * u)[None, :]])
        valid = np.append(valid, True)
    elif not valid.any():
        return None
    offsets = -np.einsum("hj,hj->h", normals, p0)  # (H,)
    # Hypotheses are scored on a subset (the winner is re-scored on every point):
    # the inlier ratio, not the count, decides, and a few hundred points estimate it well.
    # Scoring in float32 (sub-micrometre error at room scale) halves the (H, n) block, which
    # then stays below the allocator's mmap threshold for the usual few hundred hypotheses.
    # An evenly strided subset: clouds come in spatial order (voxel keys, image rows), so it
    # spreads over the whole cloud, and costs nothing to draw.
    S = P if n_pts <= _SCORE_POINTS else P[:: -(-n_pts // _SCORE_POINTS)]
    S32 = S.T.astype(np.float32)  # (3, n)
    n32, o32 = normals.astype(np.float32), offsets.astype(np.float32)
    counts = np.zeros(len(normals), np.float32)
    step = max(1, _MAX_BLOCK // max(1, len(S)))
    d32 = np.float32(distance_m)
    ones = np.ones(len(S), np.float32)
    for s in range(0, len(normals), step):
        d = n32[s : s + step] @ S32  # (h, n)
        d += o32[s : s + step, None]
        # Inliers counted by a matrix-vector product with ones: exact for integers below
        # 2**24 and a third of count_nonzero(axis=1)'s cost on these small blocks.
        counts[s : s + step] = (np.abs(d, out=d) <= d32).astype(np.float32) @ ones
    counts[~valid] = -1.0
    best = int(np.argmax(counts))
    n, off = normals[best], float(offsets[best])
    inliers = np.abs(P @ n + off) <= distance_m
    n_in = int(np.count_nonzero(inliers))
    if n_in < max(3, min_inliers):
        return None
    n_ref, off_ref = _refine(P[inliers])
    if u is not None:
        if n_ref @ u < 0:
            n_ref, off_ref = -n_ref, -off_ref
        if abs(float(n_ref @ u)) < math.cos(max_tilt_rad) - 1e-9:
            n_ref, off_ref = n, off  # refinement tilted too far: keep the hypothesis
    inliers_ref = np.abs(P @ n_ref + off_ref) <= distance_m
    n_ref_in = int(np.count_nonzero(inliers_ref))
    if n_ref_in >= n_in:
        n, off, inliers, n_in = n_ref, off_ref, inliers_ref, n_ref_in
    if n_in < min_inliers:
        return None
    plane = Plane((float(n[0]), float(n[1]), float(n[2])), off)
    return PlaneFit(plane, inliers)


def estimate_floor(
    points_m: NDArray[np.floating],
    up_hint: NDArray[np.floating],
    max_tilt_rad: float = math.radians(35.0),
    distance_m: float = 0.03,
    iterations: int = 300,
    bin_m: float = 0.04,
    min_support_frac: float = 0.04,
    rng: np.random.Generator | None = None,
) -> PlaneFit:
    """The floor: the lowest large near-horizontal plane of a scene cloud (N, 3).

    ``up_hint`` (3,) is roughly up in the points' frame (e.g. -y of a level optical camera);
    the floor may be tilted up to ``max_tilt_rad`` from it. First the dominant near-horizontal
    plane gives the up direction (a table top and the floor are parallel), then the histogram
    of heights along it picks the lowest height holding at least ``min_support_frac`` of the
    points, and a plane is fitted to the points around that height. The returned normal points
    up. Raises :class:`MapError` when no such plane exists.
    """
    P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    rng = rng if rng is not None else np.random.default_rng(0)
    dominant = fit_plane(P, distance_m, iterations, rng, up=up_hint, max_tilt_rad=max_tilt_rad,
                         min_inliers=max(3, int(min_support_frac * len(P))))
    if dominant is None:
        raise MapError(
            f"no near-horizontal plane within {math.degrees(max_tilt_rad):.0f} deg of the up hint "
            f"among {len(P)} points: cannot estimate the floor"
        )
    up = dominant.plane.normal_array
    h = P @ up  # (N,)
    lo, hi = float(h.min()), float(h.max())
    n_bins = max(1, int(math.ceil((hi - lo) / bin_m)))
    counts, edges = np.histogram(h, bins=n_bins, range=(lo, lo + n_bins * bin_m))
    # Two adjacent bins, so a plane straddling a bin edge is not split in half.
    pair = counts + np.concatenate([counts[1:], [0]])
    need = min_support_frac * len(P)
    candidates = np.nonzero(pair >= need)[0]
    if len(candidates) == 0:
        raise MapError(f"no height band holds {min_support_frac:.0%} of the points: no floor found")
    k = int(candidates[0])
    band = (h >= edges[k] - bin_m) & (h <= edges[k] + 3 * bin_m)
    floor = fit_plane(P[band], distance_m, iterations, rng, up=up, max_tilt_rad=math.radians(5.0),
                      min_inliers=max(3, int(0.5 * need)))
    if floor is None:
        raise MapError("the lowest supported height band holds no plane: no floor found")
    inliers = np.zeros(len(P), bool)
    inliers[np.nonzero(band)[0][floor.inliers]] = True
    return PlaneFit(floor.plane, inliers)


def gravity_aligned_frame(
    floor: Plane, forward_hint: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> Transform:
    """``T_map_world`` (4, 4) for a map frame whose z is the floor normal (up) and whose
    origin lies on the floor below the world origin.

    ``floor`` is given in the world frame. The map x axis is ``forward_hint`` (3, world frame;
    default +z, the optical axis of a camera-defined world) projected onto the floor, y = z x x.
    Heights in the resulting map frame are true heights above the floor.
    """
    z = floor.normal_array / np.linalg.norm(floor.normal_array)
    f = np.asarray(forward_hint, dtype=np.float64)
    x = f - (f @ z) * z
    if np.linalg.norm(x) < 1e-6:
        raise ValueError("forward_hint is parallel to the floor normal")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    origin = -floor.offset_m * z  # the floor point closest to the world origin
    return invert(make_transform(np.stack([x, y, z], axis=1), origin))
