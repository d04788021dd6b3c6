"""Plane fitting by RANSAC, floor estimation and the gravity-aligned map frame.

A plane is ``normal . p + offset_m = 0`` with a unit ``normal``; for horizontal planes the
normal points up, so ``normal . p + offset_m`` is the signed height of ``p`` above the plane.
The hypotheses are built and voted on in one numba-compiled call (:func:`_best_hypothesis`;
compiled once and cached, see :mod:`semmap.clustering`): a hundred hypotheses on a few
hundred points, where a numpy expression per step cost more in calls than in arithmetic.
With an ``up`` direction the hypotheses are constrained near horizontal (tilt at most
``max_tilt_rad``), and the best exactly-horizontal plane (every point's height tried, by a
window count on sorted heights) joins them, so a seat or table top wins even when most points
lie on vertical surfaces (backrests, legs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.errors import MapError
from semmap.frames import Transform, invert, make_transform

#: Points on which hypotheses are scored (an evenly strided subset: clouds come in spatial
#: order, voxel keys or image rows, so it spreads over the whole cloud; the winner is then
#: re-scored on every point). The inlier ratio, not the count, decides, and a few hundred
#: points estimate it well.
_SCORE_POINTS = 256


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


@numba.njit(cache=True)
def _best_hypothesis(
    P: NDArray[np.float64], idx: NDArray[np.int64], distance_m: float, u: NDArray[np.float64],
    use_up: bool, min_cos: float, stride: int, out_normal: NDArray[np.float64],
) -> tuple[bool, float]:
    """The winning plane hypothesis of :func:`fit_plane`: ``(found, offset)``, its normal
    written to ``out_normal`` (3,).

    ``P`` (N, 3) points, ``idx`` (H, 3) the drawn triples. Each triple's plane (normal by
    the cross product; degenerate triples rejected), with ``use_up`` oriented towards the
    unit ``u`` and rejected when ``|n . u| < min_cos``, followed by the best exactly
    horizontal plane (every point's height tried, support by a window sweep on the sorted
    heights). The vote counts, in float32, the points of the strided subset ``P[::stride]``
    within ``distance_m``; the first hypothesis with most votes wins. Everything but the
    random draw, compiled: a hundred hypotheses on a few hundred points, where numpy's
    per-call cost exceeded the arithmetic.
    """
    n_hyp = idx.shape[0]
    normals = np.empty((n_hyp + 1, 3))
    offsets = np.empty(n_hyp + 1)
    valid = np.zeros(n_hyp + 1, np.bool_)
    _triple_planes(P, idx, u, use_up, min_cos, normals, offsets, valid)
    if use_up:
        h_best = _densest_height(P, u, distance_m)
        normals[n_hyp, 0], normals[n_hyp, 1], normals[n_hyp, 2] = u[0], u[1], u[2]
        q0, q1, q2 = h_best * u[0], h_best * u[1], h_best * u[2]  # the plane's point on the up axis
        offsets[n_hyp] = -(u[0] * q0 + u[1] * q1 + u[2] * q2)
        valid[n_hyp] = True
    best = _most_votes(P, normals, offsets, valid, distance_m, stride)
    if best < 0:
        return False, 0.0
    out_normal[0], out_normal[1], out_normal[2] = normals[best, 0], normals[best, 1], normals[best, 2]
    return True, offsets[best]


@numba.njit(cache=True)
def _triple_planes(
    P: NDArray[np.float64], idx: NDArray[np.int64], u: NDArray[np.float64], use_up: bool, min_cos: float,
    normals: NDArray[np.float64], offsets: NDArray[np.float64], valid: NDArray[np.bool_],
) -> None:
    """Writes each drawn triple's plane (unit normal, offset) and marks it valid unless it is
    degenerate or, with ``use_up``, tilted beyond ``min_cos`` from ``u`` (normal towards ``u``)."""
    for h in range(idx.shape[0]):
        i0, i1, i2 = idx[h, 0], idx[h, 1], idx[h, 2]
        ax, ay, az = P[i1, 0] - P[i0, 0], P[i1, 1] - P[i0, 1], P[i1, 2] - P[i0, 2]
        bx, by, bz = P[i2, 0] - P[i0, 0], P[i2, 1] - P[i0, 1], P[i2, 2] - P[i0, 2]
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        if norm <= 1e-12:
            continue
        nx, ny, nz = nx / norm, ny / norm, nz / norm
        if use_up:
            dot = nx * u[0] + ny * u[1] + nz * u[2]
            if dot < 0:
                nx, ny, nz = -nx, -ny, -nz
            if abs(dot) < min_cos:
                continue
        normals[h, 0], normals[h, 1], normals[h, 2] = nx, ny, nz
        offsets[h] = -(nx * P[i0, 0] + ny * P[i0, 1] + nz * P[i0, 2])
        valid[h] = True


@numba.njit(cache=True)
def _densest_height(P: NDArray[np.float64], u: NDArray[np.float64], distance_m: float) -> float:
    """The point height along ``u`` with the most points within ``distance_m`` of it (the
    first such), by a window sweep on the sorted heights."""
    n_pts = P.shape[0]
    hs = np.empty(n_pts)
    for j in range(n_pts):
        hs[j] = P[j, 0] * u[0] + P[j, 1] * u[1] + P[j, 2] * u[2]
    hs.sort()
    best_support, h_best = -1, 0.0
    lo_j, hi_j = 0, 0
    for j in range(n_pts):
        while hs[lo_j] < hs[j] - distance_m:
            lo_j += 1
        while hi_j < n_pts and hs[hi_j] <= hs[j] + distance_m:
            hi_j += 1
        if hi_j - lo_j > best_support:
            best_support, h_best = hi_j - lo_j, hs[j]
    return h_best


@numba.njit(cache=True)
def _most_votes(
    P: NDArray[np.float64], normals: NDArray[np.float64], offsets: NDArray[np.float64], valid: NDArray[np.bool_],
    distance_m: float, stride: int,
) -> int:
    """The first valid hypothesis with the most points of ``P[::stride]`` within
    ``distance_m`` (float32 distances), or -1 when none is valid."""
    d32 = np.float32(distance_m)
    best, best_count = -1, -1
    for h in range(normals.shape[0]):
        if not valid[h]:
            continue
        n0, n1, n2 = np.float32(normals[h, 0]), np.float32(normals[h, 1]), np.float32(normals[h, 2])
        o = np.float32(offsets[h])
        count = 0
        for j in range(0, P.shape[0], stride):
            # float32 arithmetic as numpy's float32 block had it (numba computes float32
            # products and sums in float64; each step is rounded back).
            dist = np.float32(np.float32(n0 * np.float32(P[j, 0])) + np.float32(n1 * np.float32(P[j, 1])))
            dist = np.float32(np.float32(dist + np.float32(n2 * np.float32(P[j, 2]))) + o)
            if abs(dist) <= d32:
                count += 1
        if count > best_count:
            best, best_count = h, count
    return best


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
    u: NDArray[np.float64] | None = None
    if up is not None:
        u = np.asarray(up, dtype=np.float64)
        u = u / np.linalg.norm(u)
    # Hypotheses from the drawn triples, the tilt constraint, the exhaustive horizontal
    # hypothesis and the vote: one compiled call (see _best_hypothesis).
    n = np.empty(3)
    found, off = _best_hypothesis(
        P, idx, float(distance_m), u if u is not None else np.zeros(3), u is not None,
        math.cos(max_tilt_rad) - 1e-12, -(-n_pts // _SCORE_POINTS), n,
    )
    if not found:
        return None
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
