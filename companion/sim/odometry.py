"""Odometry drift of the simulated autopilot: what an indoor EKF without GPS reports.

The reported pose integrates the true motion with a scale error, a heading that drifts at a
constant rate, and random-walk noise: each increment of the true pose (x, y, yaw) is rotated
by the current heading error, scaled by ``1 + scale_error`` and perturbed, then added to the
reported pose. Roll, pitch and height are not affected (the IMU and the range finder keep
them). Seeded, so a flight's drift is repeatable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from semmap.frames import wrap_angle_rad


@dataclass
class OdometryDriftModel:
    """Stateful drift: call :meth:`update` with the true pose at increasing times.

    ``scale_error``: fractional (0.03 = travelled distances read 3 % long).
    ``heading_drift_deg_s``: reported yaw minus true yaw grows at this rate.
    ``noise_m_per_sqrt_m``/``noise_rad_per_sqrt_rad``: random-walk noise per unit of motion.
    """

    scale_error: float = 0.03
    heading_drift_deg_s: float = 0.5
    noise_m_per_sqrt_m: float = 0.005
    noise_rad_per_sqrt_rad: float = 0.005
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _last_true: NDArray[np.float64] | None = field(default=None, init=False, repr=False)
    _reported: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3), init=False, repr=False)
    _t0: float = field(default=0.0, init=False, repr=False)
    _yaw_noise: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def heading_error_rad(self, t_s: float) -> float:
        """Reported minus true yaw at ``t_s`` (drift plus accumulated noise)."""
        return math.radians(self.heading_drift_deg_s) * (t_s - self._t0) + self._yaw_noise

    def update(self, t_s: float, true_pose: tuple[float, float, float] | NDArray[np.float64]) -> NDArray[np.float64]:
        """The reported (3,) x_m, y_m, yaw_rad for the true (x_m, y_m, yaw_rad) at ``t_s``. The
        first call anchors the reported pose to the true one."""
        p = np.asarray(true_pose, dtype=np.float64).reshape(3)
        if self._last_true is None:
            self._last_true = p.copy()
            self._reported = p.copy()
            self._t0 = float(t_s)
            return p.copy()
        d_xy = p[:2] - self._last_true[:2]
        d_yaw = wrap_angle_rad(float(p[2] - self._last_true[2]))
        dist = float(np.hypot(*d_xy))
        self._yaw_noise += float(self._rng.normal(0.0, self.noise_rad_per_sqrt_rad * math.sqrt(abs(d_yaw) + dist)))
        err = self.heading_error_rad(t_s)
        c, s = math.cos(err), math.sin(err)
        step = (1.0 + self.scale_error) * np.array([c * d_xy[0] - s * d_xy[1], s * d_xy[0] + c * d_xy[1]])
        step += self._rng.normal(0.0, self.noise_m_per_sqrt_m * math.sqrt(dist), size=2)
        self._reported[:2] += step
        self._reported[2] = wrap_angle_rad(float(p[2]) + err)
        self._last_true = p.copy()
        return self._reported.copy()
