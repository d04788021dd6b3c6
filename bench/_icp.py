"""Point-to-plane ICP on 3D point clouds (numpy + scipy's cKDTree, no Open3D).

Used to recover the relative motion between two depth frames (the TUM fr1/xyz check of the
SLAM issue: the handheld motion there is fully 3D, which a 2D band scan cannot see). The
registration is coarse to fine over voxel sizes; each level runs Gauss-Newton on the
linearised point-to-plane error ``n_i . (R p_i + t - q_i)`` with Huber weights and a
correspondence distance that shrinks with the voxel size.

Conventions: ``source`` and ``target`` clouds are (N, 3) metres in their own sensor frames;
the result ``T_target_source`` (4, 4) maps source points into the target frame. For two
frames of a camera, ``T_prev_curr = register(curr cloud, prev cloud)``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from semmap.errors import PerceptionError
from semmap.pointcloud import backproject
from semmap.types import CameraIntrinsics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IcpResult:
    """Outcome of :func:`icp_point_to_plane`.

    ``T_target_source``: (4, 4). ``rmse_m``: RMS point-to-plane distance of the inliers.
    ``fitness``: fraction of source points with a correspondence. ``information``: (6, 6)
    J^T W J of the last iteration in (rotation rad, translation m) order: its smallest
    eigenvalue tells how well the geometry constrains the motion (a plane constrains 3 of 6).
    """

    T_target_source: NDArray[np.float64]
    rmse_m: float
    fitness: float
    n_iterations: int
    converged: bool
    information: NDArray[np.float64]


def voxel_downsample(points_m: NDArray[np.floating], voxel_m: float) -> NDArray[np.float64]:
    """(M, 3) centroids of the points in each occupied voxel of edge ``voxel_m``; (N, 3) in."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if voxel_m <= 0.0 or len(pts) == 0:
        return pts.copy()
    keys = np.floor(pts / voxel_m).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, pts)
    return sums / counts[:, None]


def estimate_normals(
    points_m: NDArray[np.floating], k: int = 12, tree: cKDTree | None = None,
    max_radius_m: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Unit normals of (N, 3) points from the PCA of their ``k`` nearest neighbours.

    Returns ``(normals (N, 3), ok (N,))``; ``ok`` is False where fewer than 5 neighbours lie
    within ``max_radius_m`` or the neighbourhood is not planar (smallest eigenvalue more
    than a third of the middle one). Normals are oriented towards the sensor at the origin.
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n < 5:
        return np.zeros((n, 3)), np.zeros(n, bool)
    tree = tree if tree is not None else cKDTree(pts)
    kk = min(k, n)
    dist, idx = tree.query(pts, k=kk, distance_upper_bound=max_radius_m)
    valid = np.isfinite(dist)  # (N, k)
    idx = np.where(valid, idx, 0)
    nb = pts[idx]  # (N, k, 3)
    w = valid.astype(np.float64)[..., None]
    cnt = np.maximum(w.sum(axis=1), 1.0)  # (N, 1)
    mean = (nb * w).sum(axis=1) / cnt
    d = (nb - mean[:, None, :]) * w
    cov = np.einsum("nki,nkj->nij", d, d) / cnt[:, :, None]
    evals, evecs = np.linalg.eigh(cov)  # ascending
    normals = evecs[:, :, 0]
    flip = np.einsum("ni,ni->n", normals, pts) > 0.0
    normals[flip] *= -1.0
    ok = (valid.sum(axis=1) >= 5) & (evals[:, 0] < evals[:, 1] / 3.0)
    return normals, ok


def _se3_exp(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(4, 4) transform of a (6,) increment (rotation vector rad, translation m)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def icp_point_to_plane(
    source_m: NDArray[np.floating],
    target_m: NDArray[np.floating],
    T_init: NDArray[np.float64] | None = None,
    max_correspondence_m: float = 0.05,
    max_iterations: int = 30,
    huber_m: float = 0.01,
    tolerance: float = 1e-6,
    target_normals: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None,
) -> IcpResult:
    """Align (N, 3) ``source_m`` to (M, 3) ``target_m`` (point-to-plane, Huber-weighted).

    ``T_init``: (4, 4) initial ``T_target_source``. Correspondences are nearest target points
    within ``max_correspondence_m`` with a planar normal. Stops when the increment is below
    ``tolerance`` (rad / m). Raises :class:`PerceptionError` when too few points correspond.
    """
    src = np.asarray(source_m, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(target_m, dtype=np.float64).reshape(-1, 3)
    if len(src) < 6 or len(tgt) < 6:
        raise PerceptionError(f"ICP needs at least 6 points per cloud (got {len(src)} and {len(tgt)})")
    tree = cKDTree(tgt)
    normals, n_ok = target_normals if target_normals is not None else estimate_normals(tgt, tree=tree)
    T = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64).copy()
    info = np.zeros((6, 6))
    rmse, fitness, converged, it = np.inf, 0.0, False, 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - reported below
        p = src @ T[:3, :3].T + T[:3, 3]
        dist, idx = tree.query(p, distance_upper_bound=max_correspondence_m)
        ok = np.isfinite(dist)
        ok[ok] &= n_ok[idx[ok]]
        if int(ok.sum()) < 6:
            raise PerceptionError(
                f"ICP: only {int(ok.sum())} of {len(src)} points have a correspondence within "
                f"{max_correspondence_m:.3f} m"
            )
        ps, q, nq = p[ok], tgt[idx[ok]], normals[idx[ok]]
        r = np.einsum("ni,ni->n", ps - q, nq)  # (K,)
        J = np.concatenate([np.cross(ps, nq), nq], axis=1)  # (K, 6)
        a = np.abs(r)
        w = np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12))
        H = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        try:
            x = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError as exc:
            raise PerceptionError("ICP: singular normal equations") from exc
        T = _se3_exp(x) @ T
        info = H
        rmse = float(np.sqrt(np.mean(r**2)))
        fitness = float(ok.mean())
        if float(np.linalg.norm(x)) < tolerance:
            converged = True
            break
    return IcpResult(T, rmse, fitness, it, converged, info)


def register_clouds(
    source_m: NDArray[np.floating], target_m: NDArray[np.floating],
    T_init: NDArray[np.float64] | None = None,
    voxels_m: Sequence[float] = (0.04, 0.02, 0.01),
    correspondence_factor: float = 2.5, max_iterations: int = 30,
) -> IcpResult:
    """Coarse-to-fine point-to-plane ICP: one :func:`icp_point_to_plane` per voxel size,
    correspondences within ``correspondence_factor`` voxels. Clouds (N, 3) / (M, 3) metres;
    returns the finest level's result (``T_target_source``)."""
    T = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64)
    result: IcpResult | None = None
    for voxel in voxels_m:
        s = voxel_downsample(source_m, voxel)
        t = voxel_downsample(target_m, voxel)
        tree = cKDTree(t)
        normals = estimate_normals(t, k=12, tree=tree, max_radius_m=4.0 * voxel)
        result = icp_point_to_plane(
            s, t, T, max_correspondence_m=correspondence_factor * voxel,
            max_iterations=max_iterations, huber_m=max(voxel / 2.0, 0.005), target_normals=normals,
        )
        T = result.T_target_source
        log.debug("ICP level %.3f m: %d iterations, rmse %.4f m, fitness %.2f",
                  voxel, result.n_iterations, result.rmse_m, result.fitness)
    if result is None:
        raise PerceptionError("register_clouds needs at least one voxel size")
    return result


def register_depth_frames(
    depth_source_m: NDArray[np.floating], depth_target_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics, min_depth_m: float = 0.3, max_depth_m: float = 4.0,
    stride_px: int = 2, voxels_m: Sequence[float] = (0.04, 0.02, 0.01),
) -> IcpResult:
    """Relative motion of a depth camera between two (H, W) depth images (metres, optical
    frame): ``T_target_source`` maps points of the source frame's camera into the target's.
    For consecutive frames pass (current, previous) to get ``T_prev_curr``."""
    src, _ = backproject(depth_source_m, intrinsics, min_depth_m, max_depth_m, stride_px=stride_px)
    tgt, _ = backproject(depth_target_m, intrinsics, min_depth_m, max_depth_m, stride_px=stride_px)
    return register_clouds(src, tgt, voxels_m=voxels_m)
