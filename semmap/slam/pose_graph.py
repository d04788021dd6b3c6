"""SPA-style 2D pose graph: submap and node poses tied by relative-pose constraints.

Each constraint says "pose b seen from pose a is z": the residual is

    e = [ R_a^T (t_b - t_a) - z_xy ;  wrap(yaw_b - yaw_a - z_yaw) ] * [w_t, w_t, w_r]

(Konolige et al., "Efficient Sparse Pose Adjustment for 2D Mapping", IROS 2010). The solver is
Levenberg-Marquardt on the sparse normal equations with an analytic Jacobian (a sparse
Cholesky-like direct solve via scipy). Loop-closure constraints carry a Huber loss
(iteratively reweighted), so one wrong closure cannot drag the map; intra-submap and
consecutive-node constraints from local SLAM are trusted (quadratic), as in Cartographer.
The first ``n_fixed`` poses are held (the gauge: the map frame is where the first submap is).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import spsolve

from semmap.errors import MapError
from semmap.slam.pose2d import wrap

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Edge:
    """Relative-pose constraint between variables ``a`` and ``b`` (indices into the pose
    array): ``z`` (3,) is b seen from a; weights are 1/sigma (1/m, 1/rad); ``robust`` edges
    get the Huber loss."""

    a: int
    b: int
    z: tuple[float, float, float]
    translation_weight: float
    rotation_weight: float
    robust: bool = False


@dataclass(frozen=True)
class OptimizationResult:
    """``poses`` (P, 3) optimised; ``cost_initial``/``cost_final`` half the sum of squared
    (robustified) residuals; ``iterations`` run."""

    poses: NDArray[np.float64]
    cost_initial: float
    cost_final: float
    iterations: int


def _residuals(poses: NDArray[np.float64], a: NDArray[np.int64], b: NDArray[np.int64],
               z: NDArray[np.float64], w: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    pa, pb = poses[a], poses[b]
    c, s = np.cos(pa[:, 2]), np.sin(pa[:, 2])
    dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
    ex = c * dx + s * dy - z[:, 0]
    ey = -s * dx + c * dy - z[:, 1]
    eth = wrap(pb[:, 2] - pa[:, 2] - z[:, 2])
    e = np.stack([ex, ey, eth], axis=1) * w  # (E, 3)
    return e, c, s, dx, dy


def _huber_weights(e: NDArray[np.float64], robust: NDArray[np.bool_], k: float) -> NDArray[np.float64]:
    """(E,) IRLS weights: 1 inside the Huber scale, k/|e| beyond, for robust edges only."""
    n = np.linalg.norm(e, axis=1)
    return np.where(robust & (n > k), k / np.maximum(n, 1e-12), 1.0)


def _cost(e: NDArray[np.float64], robust: NDArray[np.bool_], k: float) -> float:
    n = np.linalg.norm(e, axis=1)
    rho = np.where(robust & (n > k), 2.0 * k * n - k * k, n * n)
    return 0.5 * float(rho.sum())


def _normal_equations(
    e: NDArray[np.float64], c: NDArray[np.float64], s: NDArray[np.float64], dx: NDArray[np.float64],
    dy: NDArray[np.float64], a: NDArray[np.int64], b: NDArray[np.int64], w: NDArray[np.float64],
    robust: NDArray[np.bool_], huber_scale: float, n_fixed: int, n_free: int,
) -> tuple[sp.csc_matrix, NDArray[np.float64]]:
    """``H = J^T J`` and ``g = J^T r`` of the (E, 3) residuals ``e`` (with :func:`_residuals`'
    terms ``c, s, dx, dy``), Huber-reweighted, over the ``n_free`` coordinates of the poses
    after the first ``n_fixed`` (the held poses have no column)."""
    E = len(a)
    # Jacobian blocks (E, 3, 3) wrt pose a and pose b, before the weights.
    Ja = np.zeros((E, 3, 3))
    Jb = np.zeros((E, 3, 3))
    Ja[:, 0, 0], Ja[:, 0, 1], Ja[:, 0, 2] = -c, -s, -s * dx + c * dy
    Ja[:, 1, 0], Ja[:, 1, 1], Ja[:, 1, 2] = s, -c, -c * dx - s * dy
    Ja[:, 2, 2] = -1.0
    Jb[:, 0, 0], Jb[:, 0, 1] = c, s
    Jb[:, 1, 0], Jb[:, 1, 1] = -s, c
    Jb[:, 2, 2] = 1.0
    Ja *= w[:, :, None]
    Jb *= w[:, :, None]
    sw = np.sqrt(_huber_weights(e, robust, huber_scale))[:, None]
    rows = np.repeat(np.arange(3 * E).reshape(E, 3), 3, axis=1).reshape(E, 3, 3)
    cols_a = (3 * (a - n_fixed))[:, None, None] + np.arange(3)[None, None, :]
    cols_b = (3 * (b - n_fixed))[:, None, None] + np.arange(3)[None, None, :]
    vals = np.concatenate([(Ja * sw[:, :, None]).ravel(), (Jb * sw[:, :, None]).ravel()])
    rr = np.concatenate([rows.ravel(), rows.ravel()])
    cc = np.concatenate([np.broadcast_to(cols_a, (E, 3, 3)).ravel(), np.broadcast_to(cols_b, (E, 3, 3)).ravel()])
    keep = cc >= 0
    J = sp.csr_matrix((vals[keep], (rr[keep], cc[keep])), shape=(3 * E, n_free))
    r = (e * sw).ravel()
    return (J.T @ J).tocsc(), J.T @ r


def optimize(
    poses: NDArray[np.float64], edges: list[Edge], n_fixed: int = 1, huber_scale: float = 1.0,
    max_iterations: int = 20, tolerance: float = 1e-6,
) -> OptimizationResult:
    """Optimise (P, 3) ``poses`` (x_m, y_m, yaw_rad) under ``edges``; the first ``n_fixed``
    stay put. Raises :class:`MapError` for edges naming unknown poses."""
    x = np.asarray(poses, dtype=np.float64).copy()
    P = len(x)
    if not edges or P <= n_fixed:
        return OptimizationResult(x, 0.0, 0.0, 0)
    a = np.array([e.a for e in edges], dtype=np.int64)
    b = np.array([e.b for e in edges], dtype=np.int64)
    if a.min() < 0 or b.min() < 0 or max(a.max(), b.max()) >= P:
        raise MapError(f"pose graph edge names a pose outside 0..{P - 1}")
    z = np.array([e.z for e in edges], dtype=np.float64)
    w = np.array([[e.translation_weight, e.translation_weight, e.rotation_weight] for e in edges])
    robust = np.array([e.robust for e in edges], dtype=bool)
    E = len(edges)
    n_free = 3 * (P - n_fixed)
    lam = 1e-4
    e, c, s, dx, dy = _residuals(x, a, b, z, w)
    cost0 = cost = _cost(e, robust, huber_scale)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - reported below
        H, g = _normal_equations(e, c, s, dx, dy, a, b, w, robust, huber_scale, n_fixed, n_free)
        improved = False
        while lam < 1e8:
            A = H + lam * sp.diags(H.diagonal() + 1e-9)
            step = -spsolve(A.tocsc(), g)
            if not np.all(np.isfinite(step)):
                lam *= 10.0
                continue
            xn = x.copy()
            xn[n_fixed:] += step.reshape(-1, 3)
            xn[:, 2] = wrap(xn[:, 2])
            en, cn, sn, dxn, dyn = _residuals(xn, a, b, z, w)
            cost_n = _cost(en, robust, huber_scale)
            if cost_n <= cost:
                x, e, c, s, dx, dy = xn, en, cn, sn, dxn, dyn
                improved = cost - cost_n > tolerance * max(cost, 1e-12)
                cost = cost_n
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if not improved or float(np.max(np.abs(step))) < tolerance:
            break
    log.debug("pose graph: %d poses, %d edges, cost %.4g -> %.4g in %d iterations", P, E, cost0, cost, it)
    return OptimizationResult(x, cost0, cost, it)
