"""BoT-SORT's Kalman filter on image boxes, vectorised over tracks.

State ``[x, y, w, h, vx, vy, vw, vh]``: box centre, width and height in pixels and their
per-frame velocities; constant-velocity motion with a one-frame step. The noise model is
BoT-SORT's (``KalmanFilter`` of its ``xywh`` tracker): every standard deviation is a fixed
fraction of the box width or height, ``std_weight_position = 1/20`` for positions and
``std_weight_velocity = 1/160`` for velocities, so big boxes (near objects) may move more
pixels than small ones. Measurements are ``[x, y, w, h]``.

All functions take stacks: ``means`` (M, 8), ``covs`` (M, 8, 8), so a frame's tracks are
predicted and updated with a handful of numpy calls.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

STD_WEIGHT_POSITION = 1.0 / 20.0
STD_WEIGHT_VELOCITY = 1.0 / 160.0

#: Constant-velocity transition for one frame, (8, 8).
F = np.eye(8)
F[:4, 4:] = np.eye(4)
#: Measurement matrix, (4, 8).
H = np.eye(4, 8)


def _wh4(means: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 4) [w, h, w, h] of each state: the scale of BoT-SORT's noise."""
    return means[:, [2, 3, 2, 3]]


def initiate(measurements: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """New tracks from (M, 4) ``[x, y, w, h]`` boxes: means (M, 8), covariances (M, 8, 8)."""
    z = np.asarray(measurements, dtype=np.float64).reshape(-1, 4)
    m = z.shape[0]
    means = np.zeros((m, 8))
    means[:, :4] = z
    wh = _wh4(means)
    std = np.concatenate([2.0 * STD_WEIGHT_POSITION * wh, 10.0 * STD_WEIGHT_VELOCITY * wh], axis=1)
    covs = np.zeros((m, 8, 8))
    idx = np.arange(8)
    covs[:, idx, idx] = std**2
    return means, covs


def predict(
    means: NDArray[np.float64], covs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One-frame prediction of (M, 8) means and (M, 8, 8) covariances (new arrays)."""
    if means.shape[0] == 0:
        return means.copy(), covs.copy()
    wh = _wh4(means)
    q = np.concatenate([STD_WEIGHT_POSITION * wh, STD_WEIGHT_VELOCITY * wh], axis=1) ** 2
    new_means = means @ F.T
    new_covs = F @ covs @ F.T
    idx = np.arange(8)
    new_covs[:, idx, idx] += q
    return new_means, new_covs


def project(
    means: NDArray[np.float64], covs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Measurement-space means (M, 4) and innovation covariances (M, 4, 4)."""
    r = (STD_WEIGHT_POSITION * _wh4(means)) ** 2
    s = covs[:, :4, :4].copy()
    idx = np.arange(4)
    s[:, idx, idx] += r
    return means[:, :4].copy(), s


def update(
    means: NDArray[np.float64], covs: NDArray[np.float64], measurements: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Correct (M, 8) means / (M, 8, 8) covariances with (M, 4) ``[x, y, w, h]`` measurements."""
    z_pred, s = project(means, covs)
    pht = covs[:, :, :4]  # P H^T, (M, 8, 4)
    # K = P H^T S^-1, solved rather than inverted: S is SPD, K^T = S^-1 (P H^T)^T.
    gain = np.linalg.solve(s, pht.transpose(0, 2, 1)).transpose(0, 2, 1)  # (M, 8, 4)
    innov = np.asarray(measurements, dtype=np.float64) - z_pred
    new_means = means + np.einsum("mij,mj->mi", gain, innov)
    new_covs = covs - gain @ s @ gain.transpose(0, 2, 1)
    return new_means, new_covs


def gating_distance(
    mean: NDArray[np.float64], cov: NDArray[np.float64], measurements: NDArray[np.float64],
    only_position: bool = False,
) -> NDArray[np.float64]:
    """Squared Mahalanobis distances (N,) of (N, 4) measurements from one (8,) state."""
    z_pred, s = project(mean[None], cov[None])
    z, s0 = z_pred[0], s[0]
    d = np.asarray(measurements, dtype=np.float64) - z
    if only_position:
        z, s0, d = z[:2], s0[:2, :2], d[:, :2]
    chol = np.linalg.cholesky(s0)
    y = np.linalg.solve(chol, d.T)
    return np.sum(y * y, axis=0)


def apply_warp(
    means: NDArray[np.float64], covs: NDArray[np.float64], warp: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera-motion compensation of states by a (3, 3) image motion (or a (2, 3) affine).

    Each centre is mapped through ``warp``; the (w, h), (vx, vy) and (vw, vh) pairs and the
    covariance are transformed by the motion's 2x2 Jacobian at that centre. For an affine
    motion the Jacobian is its 2x2 part everywhere and this is exactly BoT-SORT's
    ``multi_gmc``; for a homography it is the local affine approximation around each track.
    States whose centre the homography maps to or beyond the horizon (a lost track far
    outside the image) are left unchanged.
    """
    if means.shape[0] == 0:
        return means.copy(), covs.copy()
    H = np.asarray(warp, dtype=np.float64)
    if H.shape == (2, 3):
        H = np.vstack([H, [0.0, 0.0, 1.0]])
    x, y = means[:, 0], means[:, 1]
    den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    ok = den > 1e-3
    den = np.where(ok, den, 1.0)
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den
    J = np.empty((means.shape[0], 2, 2))  # d(u, v) / d(x, y) at each centre
    J[:, 0, 0] = (H[0, 0] - u * H[2, 0]) / den
    J[:, 0, 1] = (H[0, 1] - u * H[2, 1]) / den
    J[:, 1, 0] = (H[1, 0] - v * H[2, 0]) / den
    J[:, 1, 1] = (H[1, 1] - v * H[2, 1]) / den
    J[~ok] = np.eye(2)
    J8 = np.zeros((means.shape[0], 8, 8))
    for k in range(4):
        J8[:, 2 * k:2 * k + 2, 2 * k:2 * k + 2] = J
    new_means = np.einsum("mij,mj->mi", J8, means)
    new_means[:, 0] = np.where(ok, u, x)
    new_means[:, 1] = np.where(ok, v, y)
    new_covs = J8 @ covs @ J8.transpose(0, 2, 1)
    return new_means, new_covs
