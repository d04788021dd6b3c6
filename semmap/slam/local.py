"""Local SLAM: odometry prediction, scan-to-submap matching, motion filter, submaps.

For each scan (gravity-aligned body frame, :class:`~semmap.scan.BandScan`):

1. predict the pose from the previous estimate and the autopilot's odometry increment,
   corrected for the odometry's systematic errors (heading drift rate, distance scale)
   as :class:`OdometryCalibration` measures them against the matched poses;
2. match the voxel-filtered hits against the matching submap: a real-time correlative
   search over a small window, then the least-squares refinement with the prediction as prior;
3. check the fit: too few hits or a low score -> the odometry prediction is used; otherwise
   the translational information (the curvature of the match score) is eigen-decomposed: a
   direction it does not constrain (along the only wall in view, along a corridor) is taken
   from the odometry prediction and the constrained one from the match; if neither direction
   is constrained the prediction is used. The status says which (:class:`SlamStatus`);
4. insert the scan into the active submaps if the motion filter lets it through (moved far
   enough, turned enough or waited long enough since the last insertion).

Poses are in the *local* frame: it starts at the first odometry pose and is corrected by the
global SLAM (:mod:`semmap.slam.global_`) as loops close.
"""

from __future__ import annotations

import enum
import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.config import SlamConfig
from semmap.occupancy import ProbabilityTables
from semmap.scan import BandScan
from semmap.slam.correlative import real_time_correlative_match
from semmap.slam.pose2d import Pose2, compose, relative, transform_xy, wrap
from semmap.slam.refine import refine_pose
from semmap.slam.submaps import ActiveSubmaps, Submap

log = logging.getLogger(__name__)


class SlamStatus(enum.Enum):
    """How a pose was obtained."""

    #: Matched against the submap.
    OK = "ok"
    #: Matched, but one translational direction was unconstrained (one wall in view, a
    #: corridor): that direction came from the odometry prediction, the rest from the match.
    PARTIAL_ODOMETRY = "partial_odometry"
    #: The scan did not constrain the pose (degenerate or no overlap): odometry used.
    DEGENERATE_FALLBACK_ODOMETRY = "degenerate_fallback_odometry"
    #: Pure-odometry mode (configured): the autopilot's pose is trusted.
    ODOMETRY = "odometry"


@dataclass(frozen=True)
class LocalResult:
    """One scan through local SLAM.

    ``pose_local`` (3,) x_m, y_m, yaw_rad in the local frame; ``prediction_local`` the odometry
    prediction; ``inserted``: the motion filter let it into the submaps (it became a node);
    ``submaps``: indices of the submaps it went into; ``finished``: submaps it finished;
    ``score``: mean probability under the matched hits; ``min_information``: smallest
    translational eigenvalue of the fit (1/m^2); ``reason``: why a fallback happened ('').
    """

    stamp_s: float
    pose_local: Pose2
    prediction_local: Pose2
    status: SlamStatus
    inserted: bool
    submaps: tuple[int, ...]
    finished: tuple[int, ...]
    score: float
    min_information: float
    n_points: int
    reason: str = ""
    #: The scan was matched (False: it took the prediction, see ``SlamConfig.match_interval_s``).
    matched: bool = False


def voxel_filter_xy(points_xy_m: NDArray[np.floating], voxel_m: float) -> NDArray[np.float64]:
    """(M, 2) centroids of the (N, 2) points in each ``voxel_m`` square (unchanged if 0)."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if voxel_m <= 0.0 or len(pts) == 0:
        return pts
    keys = np.floor(pts / voxel_m).astype(np.int64)
    _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out = np.zeros((len(cnt), 2))
    np.add.at(out, inv, pts)
    return out / cnt[:, None]


def constrained_translation(
    information: NDArray[np.float64], matched_xy_m: NDArray[np.float64], predicted_xy_m: NDArray[np.float64],
    min_information: float, min_ratio: float,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """Split a match into the translational directions the scan constrains and the one it
    does not (the per-direction degeneracy test).

    ``information``: (3, 3) curvature of the match score at the matched pose (x, y, yaw;
    1/m^2 in the translational block); ``matched_xy_m``/``predicted_xy_m``: (2,) the match's
    and the odometry prediction's position, same frame. A direction is constrained when its
    eigenvalue of the translational block is at least ``min_information`` and at least
    ``min_ratio`` times the largest one. Returns ``(xy, free_direction)``: ``xy`` (2,) the
    match along the constrained directions plus the prediction along the free one, and
    the unit (2,) free direction (None when both are constrained); ``(None, None)`` when
    neither direction is constrained (the caller falls back to odometry)."""
    ev, vecs = np.linalg.eigh(0.5 * (information[:2, :2] + information[:2, :2].T))  # ascending
    threshold = max(float(min_information), float(min_ratio) * float(ev[1]))
    matched = np.asarray(matched_xy_m, dtype=np.float64)
    if ev[1] < threshold or ev[1] <= 0.0:
        return None, None
    if ev[0] >= threshold:
        return matched.copy(), None
    u = vecs[:, 0]
    pred = np.asarray(predicted_xy_m, dtype=np.float64)
    d = matched - pred
    return pred + d - u * float(u @ d), u.copy()


class OdometryCalibration:
    """The odometry's systematic errors, measured against the matched poses of the last
    ``window_s`` seconds: its heading drift rate (rad/s; an indoor EKF's yaw from an
    uncorrected gyro bias) and its distance scale (an optical-flow scale error).

    Why: the prediction composes the previous estimate with the odometry increment, and the
    least-squares refinement keeps a prior at that prediction. Where the scans constrain the
    yaw weakly (a narrow camera, one wall in view) every scan gives back only part of the
    increment's bias, and a drift of ``w`` rad/s leaves the estimate lagging by a multiple of
    ``w * dt``: degrees, which the vehicle flies into metres. Both errors are smooth, so they
    are measured over seconds of matched scans and taken out of the increments.

    The heading drift is the slope of (odometry yaw - matched yaw) over time (least squares
    over the window: the matched yaw's per-scan noise averages out), with one offset per
    stretch between turns faster than ``max_turn_rate_rad_s`` (:func:`_drift_between_turns`;
    kept while those stretches span less than ``min_span_s``); the scale the
    least-squares ratio of the odometry's body-frame displacements to the matched ones over
    pairs of scans ``pair_s`` apart (long enough that the match noise does not shrink it).
    Only fully matched scans (status OK) are used. Estimates are clamped to
    ``max_drift_rad_s`` and ``max_scale_error`` and stay at zero until the window holds
    ``min_span_s`` seconds of matches; the scale is kept while the pairs' RMS displacement is
    below ``min_displacement_m`` (hovering).
    """

    def __init__(self, window_s: float, min_span_s: float = 3.0, pair_s: float = 1.0,
                 max_drift_rad_s: float = math.radians(5.0), max_scale_error: float = 0.2,
                 min_displacement_m: float = 0.1, max_turn_rate_rad_s: float = math.radians(30.0)) -> None:
        self.window_s = float(window_s)
        self.max_turn_rate_rad_s = float(max_turn_rate_rad_s)
        self.min_displacement_m = float(min_displacement_m)
        self.min_span_s = float(min_span_s)
        self.pair_s = float(pair_s)
        self.max_drift_rad_s = float(max_drift_rad_s)
        self.max_scale_error = float(max_scale_error)
        #: (stamp_s, odometry pose (3,), matched local pose (3,)) of recent OK scans.
        self._samples: deque[tuple[float, Pose2, Pose2]] = deque()
        #: Odometry yaw rate minus the true one (rad/s).
        self.heading_drift_rad_s = 0.0
        #: Odometry distance / true distance - 1.
        self.scale_error = 0.0

    def correct(self, increment: Pose2, dt_s: float) -> Pose2:
        """An odometry body-frame increment (3,) over ``dt_s`` with the estimated errors
        removed."""
        out = np.asarray(increment, dtype=np.float64).copy()
        out[:2] /= 1.0 + self.scale_error
        out[2] -= self.heading_drift_rad_s * max(0.0, float(dt_s))
        return out

    def add(self, stamp_s: float, odometry_pose: Pose2, matched_pose: Pose2) -> None:
        """Record a fully matched scan and update the estimates."""
        if self.window_s <= 0.0:
            return
        s = self._samples
        s.append((float(stamp_s), np.asarray(odometry_pose, np.float64).copy(),
                  np.asarray(matched_pose, np.float64).copy()))
        while s and s[0][0] < stamp_s - self.window_s:
            s.popleft()
        if len(s) < 10 or s[-1][0] - s[0][0] < self.min_span_s:
            return
        t = np.array([x[0] for x in s])
        odo = np.array([x[1] for x in s])
        mat = np.array([x[2] for x in s])
        rate = _drift_between_turns(t, odo[:, 2], mat[:, 2], self.max_turn_rate_rad_s, self.min_span_s)
        if rate is not None:
            self.heading_drift_rad_s = float(np.clip(rate, -self.max_drift_rad_s, self.max_drift_rad_s))
        # Pairs (k, j(k)) about pair_s apart: body-frame displacement in each frame.
        j = np.searchsorted(t, t + self.pair_s)
        k = np.flatnonzero(j < len(t))
        if len(k) < 5:
            return
        j = j[k]
        d_odo = _body_displacements(odo[k], odo[j])
        d_mat = _body_displacements(mat[k], mat[j])
        den = float(np.sum(d_mat * d_mat))
        if den < len(k) * self.min_displacement_m**2:
            # Hovering or turning on the spot: the displacements are noise, keep the estimate.
            return
        ratio = float(np.sum(d_odo * d_mat)) / den
        self.scale_error = float(np.clip(ratio - 1.0, -self.max_scale_error, self.max_scale_error))


def _drift_between_turns(t: NDArray[np.float64], odo_yaw: NDArray[np.float64], mat_yaw: NDArray[np.float64],
                         max_turn_rate_rad_s: float, min_span_s: float) -> float | None:
    """The slope of (odometry yaw - matched yaw) over ``t`` (rad/s), least squares with one
    offset per stretch between turns faster than ``max_turn_rate_rad_s``; None when the
    stretches span less than ``min_span_s`` together.

    In a fast turn the narrow camera matches its heading worst and the gyro measures it best:
    a turn's matching error is a step in the difference, and a single line through it takes
    the step for drift, which is then fed into every prediction after it."""
    odo_u = np.unwrap(odo_yaw)
    turning = np.abs(np.diff(odo_u)) > max_turn_rate_rad_s * np.maximum(np.diff(t), 1e-6)
    first = np.flatnonzero(np.concatenate([[True], turning]))  # each stretch's first sample
    last = np.append(first[1:] - 1, len(t) - 1)
    if float(np.sum(t[last] - t[first])) < min_span_s:
        return None
    stretch = np.concatenate([[0], np.cumsum(turning)])
    n = np.bincount(stretch).astype(np.float64)
    diff = odo_u - np.unwrap(mat_yaw)
    tc = t - (np.bincount(stretch, t) / n)[stretch]
    dc = diff - (np.bincount(stretch, diff) / n)[stretch]
    den = float(tc @ tc)
    return float(tc @ dc) / den if den > 1e-12 else None


def _body_displacements(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(K, 2) displacement from each pose of (K, 3) ``a`` to the matching pose of ``b``, in
    ``a``'s frame."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)


class LocalSlam:
    """The local trajectory builder. Not thread-safe: one caller (the live pipeline)."""

    def __init__(self, cfg: SlamConfig, tables: ProbabilityTables | None = None) -> None:
        self.cfg = cfg
        self.submaps = ActiveSubmaps(cfg.scans_per_submap, cfg.resolution_m,
                                     tables or ProbabilityTables(), cfg.blur_sigma_cells,
                                     cfg.live_blur_sigma_cells)
        self._last_pose: Pose2 | None = None
        self._last_odom: Pose2 | None = None
        self._last_insert: tuple[float, Pose2] | None = None
        self._last_stamp_s: float | None = None
        #: When the last scan was matched with status OK (None: no such scan yet, or a
        #: later one was not OK).
        self._last_ok_match_s: float | None = None
        self.calibration = OdometryCalibration(cfg.odometry_calibration_window_s)

    @property
    def last_pose(self) -> Pose2 | None:
        """The latest local pose (3,), None before the first scan."""
        return None if self._last_pose is None else self._last_pose.copy()

    def predict(self, odometry_pose: Pose2, stamp_s: float | None = None) -> Pose2:
        """The local pose the odometry increment since the previous scan predicts (with the
        measured heading drift and scale taken out; ``stamp_s`` gives the drift's interval)."""
        if self._last_pose is None or self._last_odom is None:
            return np.asarray(odometry_pose, dtype=np.float64).copy()
        dt = 0.0 if stamp_s is None or self._last_stamp_s is None else float(stamp_s) - self._last_stamp_s
        return compose(self._last_pose, self.calibration.correct(relative(self._last_odom, odometry_pose), dt))

    def add_scan(self, stamp_s: float, scan: BandScan, odometry_pose: Pose2) -> LocalResult:
        """Estimate the pose of one scan; ``odometry_pose`` (3,) is the autopilot's (x, y, yaw)
        in its own (drifting) frame at the scan's time."""
        cfg = self.cfg
        odom = np.asarray(odometry_pose, dtype=np.float64).reshape(3)
        pred = self.predict(odom, stamp_s)
        pts = voxel_filter_xy(scan.hits_xy_m, cfg.voxel_filter_m)
        target = self.submaps.matching_submap
        status, reason, score, min_info = SlamStatus.OK, "", 0.0, 0.0
        pose = pred
        # A submap that holds no obstacle yet (its scans came from the ground, where the
        # camera sees nothing in the band) has nothing to match against: this scan is used
        # at the prediction and inserted whatever the motion filter says, so the next one
        # can be matched; waiting for the filter (up to motion_filter_time_s) would leave
        # the scans in between on the drifting odometry and anchor the map to it.
        starved = target is not None and target.n_hits < cfg.min_scan_points
        predicted = self._predicts(stamp_s)
        matched = False
        if not predicted and target is not None and target.n_scans > 0 and not starved:
            pose, status, reason, score, min_info = self._match(target, pts, pred)
            matched = True
        elif starved and target is not None:
            status = SlamStatus.DEGENERATE_FALLBACK_ODOMETRY
            reason = f"submap {target.index} holds {target.n_hits} hits: nothing to match against yet"
        self._last_pose, self._last_odom, self._last_stamp_s = pose, odom, float(stamp_s)
        if matched:
            self._last_ok_match_s = float(stamp_s) if status is SlamStatus.OK else None
        if matched and status is SlamStatus.OK:
            self.calibration.add(stamp_s, odom, pose)
        inserted = False
        into: tuple[int, ...] = ()
        finished: tuple[int, ...] = ()
        if (starved and len(pts) >= cfg.min_scan_points) or (
                not predicted and self._motion_filter_passes(stamp_s, pose)):
            ins, fin = self.submaps.insert(scan, pose)
            into = tuple(s.index for s in ins)
            finished = tuple(s.index for s in fin)
            inserted = True
            self._last_insert = (stamp_s, pose.copy())
        if status is not SlamStatus.OK:
            log.debug("scan at %.3f s: odometry fallback (%s)", stamp_s, reason)
        return LocalResult(stamp_s, pose, pred, status, inserted, into, finished, score, min_info,
                           len(pts), reason, matched)

    def _predicts(self, stamp_s: float) -> bool:
        """Whether the scan at ``stamp_s`` takes the odometry prediction instead of a match:
        it comes less than ``match_interval_s`` after an OK match.

        Each match adds an error of its own to the pose and, through the insertions, to the
        submap (the depth noise of the far walls, the end of a wall coming into view in a
        turn), and these errors add up over the matches of a turn: matching every frame of a
        30 Hz camera sums three times as many as matching at 10 Hz, while over a tenth of a
        second the odometry's increment is far more accurate than one match."""
        t0 = self._last_ok_match_s
        return t0 is not None and 0.0 <= float(stamp_s) - t0 < self.cfg.match_interval_s

    def _match(self, target: Submap, pts: NDArray[np.float64], pred: Pose2) -> tuple[
            Pose2, SlamStatus, str, float, float]:
        cfg = self.cfg
        fallback = SlamStatus.DEGENERATE_FALLBACK_ODOMETRY
        if len(pts) < cfg.min_scan_points:
            return pred, fallback, f"{len(pts)} scan points < {cfg.min_scan_points}", 0.0, 0.0
        grid = target.live_match_grid()
        init = relative(target.local_pose, pred)  # the submap frame has no rotation
        pts = _seen_by(target, pts, init, cfg.min_scan_points)
        rt_pose, _ = real_time_correlative_match(
            grid, pts, init, cfg.correlative_linear_window_m,
            math.radians(cfg.correlative_angular_window_deg),
            cfg.correlative_translation_cost, cfg.correlative_rotation_cost,
        )
        ref = refine_pose(grid, pts, rt_pose, prior_xy_m=init[:2], prior_yaw_rad=float(init[2]),
                          occupied_space_weight=cfg.occupied_space_weight,
                          translation_weight=cfg.translation_weight, rotation_weight=cfg.rotation_weight)
        score = ref.mean_probability
        lo, hi = ref.translation_eigenvalues()
        if score < cfg.min_match_score:
            return pred, fallback, f"match score {score:.2f} < {cfg.min_match_score:.2f}", score, lo
        xy, free_dir = constrained_translation(ref.information, ref.pose[:2], init[:2],
                                               cfg.min_translation_information, cfg.min_information_ratio)
        if xy is None:
            return pred, fallback, (f"degenerate fit: translational information {lo:.2f} "
                                    f"(largest {hi:.2f}) 1/m^2"), score, lo
        status, reason = SlamStatus.OK, ""
        if free_dir is not None:
            # Direction in the local frame (the submap frame has no rotation).
            status = SlamStatus.PARTIAL_ODOMETRY
            reason = (f"direction ({free_dir[0]:+.2f}, {free_dir[1]:+.2f}) unconstrained "
                      f"(information {lo:.2f} of {hi:.2f} 1/m^2): odometry along it")
        pose = compose(target.local_pose, np.array([xy[0], xy[1], ref.pose[2]]))
        pose[2] = float(wrap(pose[2]))
        return pose, status, reason, score, lo

    def _motion_filter_passes(self, stamp_s: float, pose: Pose2) -> bool:
        if self._last_insert is None:
            return True
        t0, p0 = self._last_insert
        cfg = self.cfg
        return bool(
            stamp_s - t0 >= cfg.motion_filter_time_s
            or float(np.hypot(pose[0] - p0[0], pose[1] - p0[1])) >= cfg.motion_filter_distance_m
            or abs(float(wrap(pose[2] - p0[2]))) >= math.radians(cfg.motion_filter_angle_deg)
        )


def _seen_by(target: Submap, pts: NDArray[np.float64], pose_in_submap: Pose2, min_points: int) -> NDArray[np.float64]:
    """The hits that land, at ``pose_in_submap``, where ``target`` has seen (:meth:`Submap.seen`;
    all of them when fewer than ``min_points`` do).

    A hit beyond what the submap has seen (the far end of a wall coming into view as the
    vehicle turns) says nothing about the pose, yet the likelihood field pulls it back onto
    the known end of that wall: in a turn every scan is rotated back a little, and the
    heading lags the turn."""
    seen = target.seen(transform_xy(pose_in_submap, pts))
    return pts[seen] if int(seen.sum()) >= min_points else pts
