"""Nonlinear least-squares scan-to-grid refinement (Cartographer's Ceres scan matcher).

Minimises, over (x, y, yaw) of the scan in the grid's frame,

* occupied space: ``w_occ / sqrt(N) * (1 - P(T p_i))`` for each hit ``p_i``, with ``P`` the
  bicubically interpolated matching grid (a smooth likelihood field, see
  :meth:`~semmap.slam.correlative.MatchGrid.from_hits`);
* a translation prior ``w_t * (t - t_prior)`` (the odometry prediction) and a rotation prior
  ``w_r * (yaw - yaw_prior)``,

with scipy's Levenberg-Marquardt and an analytic Jacobian. The curvature of the
occupied-space score tells whether the scan constrains the pose: in a featureless
corridor its translational part has an eigenvalue near zero along the corridor. (Its
curvature, not ``J^T J``: at a perfect fit the hits sit on the ridge where the gradient
vanishes.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from semmap.slam.correlative import MatchGrid
from semmap.slam.pose2d import Pose2, wrap


@dataclass(frozen=True)
class RefineResult:
    """``pose`` (3,) in the grid's frame; ``mean_probability`` under the hits at the pose;
    ``information`` (3, 3) the curvature of the mean probability at the pose
    (:func:`score_curvature`; 1/m^2, 1/(m rad), 1/rad^2); ``n_points`` hits used; ``success`` the solver converged."""

    pose: Pose2
    mean_probability: float
    information: NDArray[np.float64]
    n_points: int
    success: bool

    def translation_eigenvalues(self) -> tuple[float, float]:
        """(smallest, largest) eigenvalue of the translational 2x2 block of ``information``."""
        ev = np.linalg.eigvalsh(self.information[:2, :2])
        return float(ev[0]), float(ev[1])


def _catmull_rom_weights(t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(N, 4) Catmull-Rom weights of the samples at -1, 0, 1, 2 for (N,) t in [0, 1), and
    (N, 4) weights of the derivative."""
    t2, t3 = t * t, t * t * t
    w = 0.5 * np.stack([-t + 2 * t2 - t3, 2 - 5 * t2 + 3 * t3, t + 4 * t2 - 3 * t3, -t2 + t3], axis=1)
    dw = 0.5 * np.stack([-1 + 4 * t - 3 * t2, -10 * t + 9 * t2, 1 + 8 * t - 9 * t2, -2 * t + 3 * t2], axis=1)
    return w, dw


_OFFSETS = np.arange(-1, 3)


def bicubic(prob: NDArray[np.float32], cc: NDArray[np.float64]) -> tuple[
        NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Bicubic (Catmull-Rom, as Ceres' ``BiCubicInterpolator``) value and gradient of ``prob``
    (rows, cols) at (N, 2) continuous (col, row) with cell centres at integers. Returns
    ``(value, d/dcol, d/drow)``, each (N,). Unlike bilinear interpolation, whose maxima sit
    on cell centres, the cubic places a smooth peak between them: sub-cell accuracy. Points
    outside take the border value with zero gradient."""
    h, w = prob.shape
    c = np.minimum(np.maximum(cc[:, 0], 0.0), w - 1.000001)
    r = np.minimum(np.maximum(cc[:, 1], 0.0), h - 1.000001)
    inside = (cc[:, 0] == c) & (cc[:, 1] == r)
    c1 = c.astype(np.int64)
    r1 = r.astype(np.int64)
    wc, dwc = _catmull_rom_weights(c - c1)
    wr, dwr = _catmull_rom_weights(r - r1)
    cols = np.minimum(np.maximum(c1[:, None] + _OFFSETS, 0), w - 1)  # (N, 4)
    rows = np.minimum(np.maximum(r1[:, None] + _OFFSETS, 0), h - 1)
    P = prob[rows[:, :, None], cols[:, None, :]].astype(np.float64)  # (N, 4 rows, 4 cols)
    along_c = np.einsum("nij,nj->ni", P, wc)  # (N, 4): each row interpolated at c
    val = np.einsum("ni,ni->n", along_c, wr)
    d_row = np.einsum("ni,ni->n", along_c, dwr)
    d_col = np.einsum("ni,nij,nj->n", wr, P, dwc)
    return val, np.where(inside, d_col, 0.0), np.where(inside, d_row, 0.0)


def refine_pose(
    grid: MatchGrid, points_xy_m: NDArray[np.float64], initial: Pose2,
    prior_xy_m: NDArray[np.float64] | None = None, prior_yaw_rad: float | None = None,
    occupied_space_weight: float = 1.0, translation_weight: float = 10.0,
    rotation_weight: float = 40.0, max_iterations: int = 20,
) -> RefineResult:
    """Refine the pose of the (N, 2) body-frame hits in ``grid`` starting at ``initial``.

    The priors default to ``initial``. Weights as in Cartographer's
    ``ceres_scan_matcher`` options (occupied space, translation, rotation)."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    x0 = np.asarray(initial, dtype=np.float64).copy()
    if n == 0:
        return RefineResult(x0, 0.0, np.zeros((3, 3)), 0, False)
    t_prior = x0[:2].copy() if prior_xy_m is None else np.asarray(prior_xy_m, np.float64)
    th_prior = float(x0[2]) if prior_yaw_rad is None else float(prior_yaw_rad)
    # Keep the prior's angle on the same branch as the start.
    th_prior = float(x0[2]) + float(wrap(th_prior - x0[2]))
    w_occ = occupied_space_weight / math.sqrt(n)
    cache: dict[bytes, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}

    def cached(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        # The solver asks for residuals and Jacobian at the same point: evaluate once.
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _occupied_space_residuals(grid, pts, x, w_occ)
        return cache[key]

    def fun(x: NDArray[np.float64]) -> NDArray[np.float64]:
        r, _ = cached(x)
        return np.concatenate([r, translation_weight * (x[:2] - t_prior), [rotation_weight * (x[2] - th_prior)]])

    def jac(x: NDArray[np.float64]) -> NDArray[np.float64]:
        _, J = cached(x)
        prior = np.zeros((3, 3))
        prior[0, 0] = prior[1, 1] = translation_weight
        prior[2, 2] = rotation_weight
        return np.concatenate([J, prior])

    # xtol 1e-5: steps below ~0.05 mm / 0.003 deg change nothing that matters.
    sol = least_squares(fun, x0, jac=jac, method="lm", max_nfev=max_iterations * 2, xtol=1e-5, ftol=1e-10)
    pose = np.array([sol.x[0], sol.x[1], float(wrap(sol.x[2]))])
    r, _ = cached(sol.x)
    mean_p = float(1.0 - np.mean(r) / w_occ) if w_occ > 0 else 0.0
    return RefineResult(pose, mean_p, score_curvature(grid, pts, pose), n, bool(sol.success))


def _occupied_space_residuals(
    grid: MatchGrid, points_xy_m: NDArray[np.float64], pose: NDArray[np.float64], w_occ: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The (N,) occupied-space residuals ``w_occ * (1 - P(T p_i))`` of the (N, 2) body-frame
    hits at ``pose`` (x_m, y_m, yaw_rad) in ``grid``'s frame, and their (N, 3) Jacobian."""
    pts = points_xy_m
    res = grid.resolution_m
    ox, oy = grid.origin_xy_m
    c, s = math.cos(pose[2]), math.sin(pose[2])
    qx = pose[0] + c * pts[:, 0] - s * pts[:, 1]
    qy = pose[1] + s * pts[:, 0] + c * pts[:, 1]
    cc = np.stack([(qx - ox) / res - 0.5, (qy - oy) / res - 0.5], axis=1)
    val, dc, dr = bicubic(grid.probability, cc)
    dqx_dth = -s * pts[:, 0] - c * pts[:, 1]
    dqy_dth = c * pts[:, 0] - s * pts[:, 1]
    gx, gy = dc / res, dr / res
    J = np.empty((len(pts), 3))
    J[:, 0] = -w_occ * gx
    J[:, 1] = -w_occ * gy
    J[:, 2] = -w_occ * (gx * dqx_dth + gy * dqy_dth)
    return w_occ * (1.0 - val), J


def score_curvature(grid: MatchGrid, points_xy_m: NDArray[np.float64], pose: Pose2) -> NDArray[np.float64]:
    """(3, 3) minus the Hessian of the mean interpolated probability under the (N, 2) body-
    frame hits at ``pose`` with respect to (x, y, yaw): the curvature of the match score at its
    peak (the Laplace approximation of the fit's information). Along a wall the score is flat,
    across it sharply peaked; a corridor leaves one translational eigenvalue near zero. The
    translational block comes from central second differences one cell apart; the yaw terms
    from moving each hit along its tangent."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    res = grid.resolution_m
    ox, oy = grid.origin_xy_m
    c, s = math.cos(pose[2]), math.sin(pose[2])
    qx = pose[0] + c * pts[:, 0] - s * pts[:, 1]
    qy = pose[1] + s * pts[:, 0] + c * pts[:, 1]
    col, row = (qx - ox) / res - 0.5, (qy - oy) / res - 0.5

    offsets = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))
    n = len(pts)
    cc = np.concatenate([np.stack([col + dc, row + dr], axis=1) for dc, dr in offsets])
    v = bicubic(grid.probability, cc)[0].reshape(len(offsets), n)
    p0 = v[0]
    pxx = (v[1] + v[2] - 2 * p0) / res**2
    pyy = (v[3] + v[4] - 2 * p0) / res**2
    pxy = (v[5] - v[6] - v[7] + v[8]) / (4 * res**2)
    # d q / d yaw = (-(qy - y), qx - x): the hit's tangent times its range.
    tx, ty = -(qy - pose[1]), qx - pose[0]
    h = np.zeros((3, 3))
    h[0, 0], h[1, 1], h[0, 1] = pxx.mean(), pyy.mean(), pxy.mean()
    h[0, 2] = (pxx * tx + pxy * ty).mean()
    h[1, 2] = (pxy * tx + pyy * ty).mean()
    h[2, 2] = (pxx * tx * tx + 2 * pxy * tx * ty + pyy * ty * ty).mean()
    h[1, 0], h[2, 0], h[2, 1] = h[0, 1], h[0, 2], h[1, 2]
    return -h
