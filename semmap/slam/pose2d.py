"""2D rigid poses ``(x_m, y_m, yaw_rad)`` as (3,) float64 arrays: compose, invert, apply to
points and scans.

``compose(a, b)`` is ``a (+) b`` (b expressed in a's frame), the SE(2) analogue of
``T_a @ T_b``; ``relative(a, b) = inverse(a) (+) b`` is b seen from a.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from semmap.frames import wrap_angle_rad as wrap
from semmap.scan import BandScan

Pose2 = NDArray[np.float64]  # (3,) x_m, y_m, yaw_rad


def pose2(x_m: float, y_m: float, yaw_rad: float) -> Pose2:
    """A (3,) pose."""
    return np.array([x_m, y_m, yaw_rad], dtype=np.float64)


def compose(a: Pose2, b: Pose2) -> Pose2:
    """``a (+) b``: the pose b (given in a's frame) in a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], float(wrap(a[2] + b[2]))])


def inverse(a: Pose2) -> Pose2:
    """The pose of the parent frame seen from ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], float(wrap(-a[2]))])


def relative(a: Pose2, b: Pose2) -> Pose2:
    """``inverse(a) (+) b``: pose b seen from pose a."""
    return compose(inverse(a), b)


def transform_xy(pose: Pose2, xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 2) points of the pose's frame into its parent frame."""
    p = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.stack([pose[0] + c * p[:, 0] - s * p[:, 1], pose[1] + s * p[:, 0] + c * p[:, 1]], axis=1)


def transform_scan(pose: Pose2, scan: BandScan) -> BandScan:
    """The scan's rays in the frame where its sensor frame sits at ``pose``."""
    return dataclasses.replace(
        scan, origin_xy_m=transform_xy(pose, scan.origin_xy_m)[0], near_xy_m=transform_xy(pose, scan.near_xy_m),
        far_xy_m=transform_xy(pose, scan.far_xy_m), hit_xy_m=transform_xy(pose, scan.hit_xy_m),
    )


def matrix3(pose: Pose2) -> NDArray[np.float64]:
    """(3, 3) homogeneous 2D transform of a pose."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def matrix4(pose: Pose2, z_m: float = 0.0) -> NDArray[np.float64]:
    """(4, 4) transform of a pose (rotation about z, translation (x, y, z_m))."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (pose[0], pose[1], z_m)
    return T


def from_matrix4(T: NDArray[np.float64]) -> Pose2:
    """(3,) x, y and the heading (yaw of the x axis) of a (4, 4) transform."""
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])


def interpolate(a: Pose2, b: Pose2, fraction: float) -> Pose2:
    """Linear interpolation of position and (shortest-way) heading; ``fraction`` in [0, 1]."""
    d = float(wrap(b[2] - a[2]))
    return np.array([a[0] + fraction * (b[0] - a[0]), a[1] + fraction * (b[1] - a[1]),
                     float(wrap(a[2] + fraction * d))])
