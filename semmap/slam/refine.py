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


def _catmull_rom(p0: NDArray[np.float64], p1: NDArray[np.float64], p2: NDArray[np.float64],
                 p3: NDArray[np.float64], t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cubic (Catmull-Rom) value and derivative between p1 (t = 0) and p2 (t = 1)."""
    a = 2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
    b = -p0 + 3.0 * p1 - 3.0 * p2 + p3
    c = p2 - p0
    val = 0.5 * (2.0 * p1 + c * t + a * t * t + b * t * t * t)
    der = 0.5 * (c + 2.0 * a * t + 3.0 * b * t * t)
    return val, der


def bicubic(prob: NDArray[np.float32], cc: NDArray[np.float64]) -> tuple[
        NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Bicubic (Catmull-Rom, as Ceres' ``BiCubicInterpolator``) value and gradient of ``prob``
    (rows, cols) at (N, 2) continuous (col, row) with cell centres at integers. Returns
    ``(value, d/dcol, d/drow)``, each (N,). Unlike bilinear interpolation, whose maxima sit
    on cell centres, the cubic places a smooth peak between them: sub-cell accuracy. Points
    outside take the border value with zero gradient."""
    h, w = prob.shape
    c = np.clip(cc[:, 0], 0.0, w - 1.000001)
    r = np.clip(cc[:, 1], 0.0, h - 1.000001)
    inside = (cc[:, 0] == c) & (cc[:, 1] == r)
    c1 = np.floor(c).astype(np.int64)
    r1 = np.floor(r).astype(np.int64)
    tc, tr = c - c1, r - r1
    cols = [np.clip(c1 + k, 0, w - 1) for k in (-1, 0, 1, 2)]
    rows = [np.clip(r1 + k, 0, h - 1) for k in (-1, 0, 1, 2)]
    vals, ders = [], []
    for rr in rows:
        q = [prob[rr, cl].astype(np.float64) for cl in cols]
        v, d = _catmull_rom(q[0], q[1], q[2], q[3], tc)
        vals.append(v)
        ders.append(d)
    val, d_row = _catmull_rom(vals[0], vals[1], vals[2], vals[3], tr)
    d_col, _ = _catmull_rom(ders[0], ders[1], ders[2], ders[3], tr)
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
    res = grid.resolution_m
    ox, oy = grid.origin_xy_m

    def model(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        c, s = math.cos(x[2]), math.sin(x[2])
        qx = x[0] + c * pts[:, 0] - s * pts[:, 1]
        qy = x[1] + s * pts[:, 0] + c * pts[:, 1]
        cc = np.stack([(qx - ox) / res - 0.5, (qy - oy) / res - 0.5], axis=1)
        val, dc, dr = bicubic(grid.probability, cc)
        dqx_dth = -s * pts[:, 0] - c * pts[:, 1]
        dqy_dth = c * pts[:, 0] - s * pts[:, 1]
        gx, gy = dc / res, dr / res
        J = np.empty((n, 3))
        J[:, 0] = -w_occ * gx
        J[:, 1] = -w_occ * gy
        J[:, 2] = -w_occ * (gx * dqx_dth + gy * dqy_dth)
        return w_occ * (1.0 - val), J

    def fun(x: NDArray[np.float64]) -> NDArray[np.float64]:
        r, _ = model(x)
        return np.concatenate([r, translation_weight * (x[:2] - t_prior), [rotation_weight * (x[2] - th_prior)]])

    def jac(x: NDArray[np.float64]) -> NDArray[np.float64]:
        _, J = model(x)
        prior = np.zeros((3, 3))
        prior[0, 0] = prior[1, 1] = translation_weight
        prior[2, 2] = rotation_weight
        return np.concatenate([J, prior])

    sol = least_squares(fun, x0, jac=jac, method="lm", max_nfev=max_iterations * 4, xtol=1e-6, ftol=1e-8)
    pose = np.array([sol.x[0], sol.x[1], float(wrap(sol.x[2]))])
    r, _ = model(sol.x)
    mean_p = float(1.0 - np.mean(r) / w_occ) if w_occ > 0 else 0.0
    return RefineResult(pose, mean_p, score_curvature(grid, pts, pose), n, bool(sol.success))


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

    def p_at(dc: float, dr: float) -> NDArray[np.float64]:
        return bicubic(grid.probability, np.stack([col + dc, row + dr], axis=1))[0]

    p0 = p_at(0.0, 0.0)
    pxx = (p_at(1, 0) + p_at(-1, 0) - 2 * p0) / res**2
    pyy = (p_at(0, 1) + p_at(0, -1) - 2 * p0) / res**2
    pxy = (p_at(1, 1) - p_at(1, -1) - p_at(-1, 1) + p_at(-1, -1)) / (4 * res**2)
    # d q / d yaw = (-(qy - y), qx - x): the hit's tangent times its range.
    tx, ty = -(qy - pose[1]), qx - pose[0]
    h = np.zeros((3, 3))
    h[0, 0], h[1, 1], h[0, 1] = pxx.mean(), pyy.mean(), pxy.mean()
    h[0, 2] = (pxx * tx + pxy * ty).mean()
    h[1, 2] = (pxy * tx + pyy * ty).mean()
    h[2, 2] = (pxx * tx * tx + 2 * pxy * tx * ty + pyy * ty * ty).mean()
    h[1, 0], h[2, 0], h[2, 1] = h[0, 1], h[0, 2], h[1, 2]
    return -h
