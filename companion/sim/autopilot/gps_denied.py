"""The mock autopilot without GPS: its horizontal position comes only from external vision.

With GPS off (``SYS_HAS_GPS`` 0 or ``EKF2_GPS_CTRL`` 0) and external-vision position fusion on
(``EKF2_EV_CTRL`` bit 0), PX4's EKF2 has a horizontal position only while the companion's
ODOMETRY / VISION_POSITION_ESTIMATE reaches it; :class:`VisionAiding` models what that means
for the mock, as PX4 does it:

* no position before the first vision sample is fused: PX4's pre-arm checks fail and arming
  is refused (home stays the configured origin, as an EKF origin set with
  SET_GPS_GLOBAL_ORIGIN);
* each sample is fused late, on EKF2's delayed horizon (``horizon_s`` plus ``EKF2_EV_DELAY``
  after it arrived), at its own timestamp (the estimator keeps the history), with a little
  noise in what is taken in, as EKF2's estimate jitters with its measurements;
* between samples the estimate dead-reckons (the estimator's drifting odometry); in the
  air, once no sample has been fused for :data:`DEAD_RECKONING_AFTER_S`, EKF2 carries its
  position on the IMU with the velocity error it had: the estimate walks away from the truth
  at a velocity drawn at the gap's start, unseen, and the controller flying the estimate
  takes the vehicle the other way. With optical flow fused (``EKF2_OF_CTRL`` bit 0) that
  error is far smaller (PX4 SITL, 3 s SLAM losses: 0.14-0.46 m of drift on the IMU alone,
  0.05-0.17 m with a flow sensor);
* with no sample fused for ``EKF2_NOAID_TOUT`` the position is invalid: in the air PX4's
  failsafe lands (:meth:`VisionAiding.position_lost`).

Height, roll and pitch stay PX4's own (range finder, IMU), as with ``EKF2_HGT_REF`` 2.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from companion.sim.autopilot.estimator import SimEstimator
from companion.sim.autopilot.params import ParamStore

#: EKF2's delayed horizon behind real time without an extra ``EKF2_EV_DELAY`` (seconds).
HORIZON_S = 0.1
#: 1-sigma noise in the position taken in per fused sample (metres).
FUSION_NOISE_M = 0.005
#: No sample fused for this long (s) in the air is a gap the IMU carries, not the camera's
#: frame interval.
DEAD_RECKONING_AFTER_S = 0.3
#: The range (m/s) of the velocity error EKF2 carries through a gap, in a random direction, on
#: the IMU alone and with optical flow fused (what the PX4 SITL drifts above took over 2-3 s).
IMU_VELOCITY_ERROR_M_S = (0.05, 0.18)
FLOW_VELOCITY_ERROR_M_S = (0.0, 0.03)
#: The parameters that turn the mock's GPS off and its vision aiding on (``EKF2_EV_CTRL`` 9:
#: horizontal position and yaw).
GPS_DENIED_PARAMS: dict[str, float] = {"SYS_HAS_GPS": 0, "EKF2_GPS_CTRL": 0, "EKF2_EV_CTRL": 9, "EKF2_HGT_REF": 2}


class VisionAiding:
    """External vision as the mock's only horizontal aiding (see the module docstring);
    reads its switches from ``params`` at every call, so a PARAM_SET takes effect at once."""

    def __init__(self, params: ParamStore, estimator: SimEstimator, seed: int = 0,
                 horizon_s: float = HORIZON_S, noise_m: float = FUSION_NOISE_M) -> None:
        self.params = params
        self.estimator = estimator
        self.horizon_s = horizon_s
        self.noise_m = noise_m
        self._rng = np.random.default_rng(seed)
        #: Samples waiting for the delayed horizon: (fuse at, stamp, north, east, yaw).
        self._pending: deque[tuple[float, float, float, float, float]] = deque()
        self.last_fused_s: float | None = None
        self.fused = 0
        #: The velocity error (north, east m/s) the estimate walks with in the present gap.
        self._gap_velocity: np.ndarray | None = None
        self._last_tick_s: float | None = None

    @property
    def active(self) -> bool:
        """GPS is off: the horizontal position is vision's or none."""
        p = self.params.get
        return p("SYS_HAS_GPS") == 0 or p("EKF2_GPS_CTRL") == 0

    @property
    def fuses_position(self) -> bool:
        return int(self.params.get("EKF2_EV_CTRL")) & 1 == 1

    @property
    def delay_s(self) -> float:
        return self.horizon_s + max(0.0, self.params.get("EKF2_EV_DELAY")) * 1e-3

    def receive(self, now_s: float, stamp_s: float, north_m: float, east_m: float, yaw_rad: float) -> None:
        """A vision sample arrived at ``now_s``, taken at ``stamp_s`` (both the mock's clock)."""
        if self.fuses_position:
            self._pending.append((now_s + self.delay_s, stamp_s, north_m, east_m, yaw_rad))

    @property
    def flow_aided(self) -> bool:
        """EKF2 fuses optical flow (``EKF2_OF_CTRL`` bit 0): a velocity without vision."""
        return int(self.params.get("EKF2_OF_CTRL")) & 1 == 1

    def tick(self, now_s: float, airborne: bool = False) -> None:
        """Fuse the samples the delayed horizon has reached; ``airborne``: dead-reckon a gap."""
        while self._pending and self._pending[0][0] <= now_s:
            _, stamp, n, e, yaw = self._pending.popleft()
            dn, de = self._rng.normal(0.0, self.noise_m, 2) if self.noise_m > 0.0 else (0.0, 0.0)
            if self.estimator.fuse_vision(stamp, n + float(dn), e + float(de), yaw):
                self.last_fused_s = now_s
                self.fused += 1
        self._dead_reckon(now_s, airborne)

    def _dead_reckon(self, now_s: float, airborne: bool) -> None:
        dt = 0.0 if self._last_tick_s is None else max(0.0, now_s - self._last_tick_s)
        self._last_tick_s = now_s
        in_gap = (airborne and self.active and self.fuses_position and self.last_fused_s is not None
                  and now_s - self.last_fused_s > DEAD_RECKONING_AFTER_S)
        if not in_gap:
            self._gap_velocity = None
            return
        if self._gap_velocity is None:
            lo, hi = FLOW_VELOCITY_ERROR_M_S if self.flow_aided else IMU_VELOCITY_ERROR_M_S
            speed, heading = self._rng.uniform(lo, hi), self._rng.uniform(-np.pi, np.pi)
            self._gap_velocity = speed * np.array([np.cos(heading), np.sin(heading)])
        self.estimator.shift(float(self._gap_velocity[0] * dt), float(self._gap_velocity[1] * dt))

    def position_valid(self, now_s: float) -> bool:
        """EKF2 has a horizontal position: vision fused within ``EKF2_NOAID_TOUT``."""
        timeout_s = self.params.get("EKF2_NOAID_TOUT") * 1e-6
        return self.last_fused_s is not None and now_s - self.last_fused_s <= timeout_s

    def position_lost(self, now_s: float) -> bool:
        """Vision aided the estimate once and has not for ``EKF2_NOAID_TOUT``."""
        return self.last_fused_s is not None and not self.position_valid(now_s)
