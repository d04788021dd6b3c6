"""``Slam2D``: the SLAM's one entry point (local SLAM + background global SLAM).

Feed every scan with the autopilot's odometry pose; get the map-frame pose back with a status:

    slam = Slam2D(SlamConfig())
    est = slam.add_scan(stamp_s, level_scan, (x_odom_m, y_odom_m, yaw_odom_rad))
    est.pose_map, est.status          # (3,), SlamStatus.OK / PARTIAL_ODOMETRY / DEGENERATE_...
    slam.stats()                      # scans, fallbacks, loop closures (for status reports)

The map frame is the odometry frame at the first scan. When loop closure moves poses,
``generation`` rises and listeners are called; :meth:`Slam2D.correction` then gives the
transform that carries anything placed with an older pose into the corrected map, and
:meth:`Slam2D.trajectory` the re-anchored poses of every scan.
"""

from __future__ import annotations

import bisect
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.config import SlamConfig
from semmap.frames import pose_from_xyz_rpy
from semmap.grid import GridSpec
from semmap.occupancy import ProbabilityGrid, ProbabilityTables
from semmap.scan import BandScan
from semmap.slam.global_ import GlobalSlam
from semmap.slam.local import LocalSlam, SlamStatus, voxel_filter_xy
from semmap.slam.pose2d import (
    Pose2,
    compose,
    interpolate,
    inverse,
    matrix4,
    relative,
    transform_scan,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlamPose:
    """The estimate for one scan: ``pose_map`` (3,) x_m, y_m, yaw_rad in the map frame (ENU),
    ``status``, ``pose_local`` (3,), the ``generation`` of the global correction it used,
    whether it became a node (``inserted``), ``reason`` for a fallback, and fit figures."""

    stamp_s: float
    pose_map: Pose2
    status: SlamStatus
    pose_local: Pose2
    generation: int
    inserted: bool
    reason: str
    score: float
    min_information: float

    def T_map_body(self, z_m: float, roll_rad: float = 0.0, pitch_rad: float = 0.0) -> NDArray[np.float64]:  # noqa: N802
        """(4, 4) body pose with the SLAM's x, y, yaw and the given height and attitude."""
        p = self.pose_map
        return pose_from_xyz_rpy(float(p[0]), float(p[1]), z_m, roll_rad, pitch_rad, float(p[2]))


@dataclass(frozen=True)
class SlamStats:
    """Counters for status reports: ``scans`` seen, how many were matched fully (``ok``),
    with one direction from odometry (``partial``) or entirely from odometry
    (``fallbacks``), the current run of consecutive fallbacks, the latest status and
    fallback reason, nodes, submaps, loop closures, loop-closure searches dropped
    (worker behind), the optimisation ``generation`` and the odometry's errors as the
    calibration measures them (:class:`semmap.slam.local.OdometryCalibration`): a scale
    error far from the odometry's own says the matches under-read the motion."""

    scans: int
    ok: int
    partial: int
    fallbacks: int
    consecutive_fallbacks: int
    last_status: str
    last_reason: str
    nodes: int
    submaps: int
    loop_closures: int
    loop_searches_dropped: int
    generation: int
    odometry_scale_error: float
    odometry_heading_drift_rad_s: float


@dataclass(frozen=True)
class SubmapView:
    """A submap as the map sees it: ``pose_map`` (3,) of its frame, its grid (shared: do not
    modify), whether it is finished and how many scans it holds."""

    index: int
    pose_map: Pose2
    grid: ProbabilityGrid
    finished: bool
    n_scans: int


class Slam2D:
    """Cartographer-style 2D SLAM. :meth:`add_scan` is for one (live) caller; the queries are
    thread-safe. Use as a context manager or call :meth:`close` to stop the worker."""

    def __init__(self, cfg: SlamConfig | None = None, tables: ProbabilityTables | None = None,
                 background: bool = True) -> None:
        self.cfg = cfg or SlamConfig()
        self.tables = tables or ProbabilityTables()
        self.local = LocalSlam(self.cfg, self.tables)
        self.global_ = GlobalSlam(self.cfg, self.local.submaps.all, background=background)
        self._lock = threading.Lock()
        # Every scan: stamp, local pose, the latest node at or before it.
        self._stamps: list[float] = []
        self._local: list[Pose2] = []
        self._anchor: list[int] = []
        self._odom_origin: Pose2 | None = None
        self.n_scans = 0
        self.n_partial = 0
        self.n_fallback = 0
        self._run_of_fallbacks = 0
        self._last_status = ""
        self._last_reason = ""

    @classmethod
    def from_config(cls, cfg: SlamConfig) -> "Slam2D":
        """A SLAM with the configured options and a background loop closer."""
        return cls(cfg)

    def __enter__(self) -> "Slam2D":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the background loop closer."""
        self.global_.close()

    @property
    def generation(self) -> int:
        """Rises each time the global optimisation moved poses."""
        return self.global_.generation

    def add_listener(self, callback: Callable[[int], None]) -> None:
        """``callback(generation)`` after the global optimisation moved poses (worker thread)."""
        self.global_.add_listener(callback)

    def add_scan(self, stamp_s: float, scan: BandScan | NDArray[np.floating],
                 odometry_pose: Pose2 | tuple[float, float, float]) -> SlamPose:
        """Estimate the map pose of one scan.

        ``scan``: a :class:`~semmap.scan.BandScan` or (N, 2) hit points, both in the gravity-aligned
        body-centred frame (metres). ``odometry_pose``: the autopilot's (x_m, y_m, yaw_rad)
        in its local ENU frame at the scan's time. Never waits for loop closure."""
        odom = np.asarray(odometry_pose, dtype=np.float64).reshape(3)
        ls = scan if isinstance(scan, BandScan) else BandScan.from_points(np.asarray(scan), stamp_s=stamp_s)
        res = self.local.add_scan(stamp_s, ls, odom)
        self._count(stamp_s, res.status, res.reason)
        if res.inserted:
            pts = voxel_filter_xy(ls.hits_xy_m, self.cfg.voxel_filter_m)
            self.global_.add_node(stamp_s, res.pose_local, pts, ls, res.submaps)
        with self._lock:
            self._stamps.append(float(stamp_s))
            self._local.append(res.pose_local.copy())
            self._anchor.append(len(self.global_.nodes) - 1)
        gen = self.generation
        pose_map = self.global_.to_global(res.pose_local)
        return SlamPose(stamp_s, pose_map, res.status, res.pose_local, gen, res.inserted, res.reason,
                        res.score, res.min_information)

    def _count(self, stamp_s: float, status: SlamStatus, reason: str) -> None:
        self.n_scans += 1
        self._last_status, self._last_reason = status.value, reason
        if status is SlamStatus.PARTIAL_ODOMETRY:
            self.n_partial += 1
        if status is not SlamStatus.DEGENERATE_FALLBACK_ODOMETRY:
            if self._run_of_fallbacks >= 10:
                log.info("scan matching back at %.2f s after %d odometry fallbacks", stamp_s, self._run_of_fallbacks)
            self._run_of_fallbacks = 0
            return
        self.n_fallback += 1
        self._run_of_fallbacks += 1
        # Not silent, not a flood: the first of a run and every 50th after it.
        if self._run_of_fallbacks == 1 or self._run_of_fallbacks % 50 == 0:
            log.log(logging.WARNING if self._run_of_fallbacks > 1 else logging.INFO,
                    "SLAM: odometry fallback at %.2f s (%d in a row, %d of %d scans): %s",
                    stamp_s, self._run_of_fallbacks, self.n_fallback, self.n_scans, reason)

    def stats(self) -> SlamStats:
        """The counters (see :class:`SlamStats`)."""
        return SlamStats(self.n_scans, self.n_scans - self.n_partial - self.n_fallback, self.n_partial,
                         self.n_fallback, self._run_of_fallbacks, self._last_status, self._last_reason,
                         len(self.global_.nodes), len(self.local.submaps.all), self.loop_closures,
                         self.global_.n_dropped, self.generation, self.local.calibration.scale_error,
                         self.local.calibration.heading_drift_rad_s)

    # --- queries ---------------------------------------------------------------------

    def _pose_of_scan(self, k: int) -> Pose2:
        a = self._anchor[k]
        if a < 0:
            return self.global_.to_global(self._local[k])
        node = self.global_.nodes[a]
        return compose(node.global_pose, relative(node.local_pose, self._local[k]))

    def trajectory(self) -> NDArray[np.float64]:
        """(M, 4) stamp_s, x_m, y_m, yaw_rad of every scan so far, re-anchored to the latest
        optimisation (map frame)."""
        with self._lock, self.global_._lock:
            rows = [(self._stamps[k], *self._pose_of_scan(k)) for k in range(len(self._stamps))]
        return np.array(rows, dtype=np.float64).reshape(-1, 4)

    def optimized_trajectory(self) -> NDArray[np.float64]:
        """(K, 4) stamp_s, x_m, y_m, yaw_rad of the nodes (the pose graph's scans)."""
        with self.global_._lock:
            return np.array([(n.stamp_s, *n.global_pose) for n in self.global_.nodes]).reshape(-1, 4)

    def pose_at(self, stamp_s: float) -> Pose2:
        """Current best map pose (3,) at ``stamp_s`` (interpolated between scans, clamped)."""
        with self._lock, self.global_._lock:
            if not self._stamps:
                raise ValueError("no scans yet")
            k = bisect.bisect_left(self._stamps, stamp_s)
            if k <= 0:
                return self._pose_of_scan(0)
            if k >= len(self._stamps):
                return self._pose_of_scan(len(self._stamps) - 1)
            t0, t1 = self._stamps[k - 1], self._stamps[k]
            f = 0.0 if t1 <= t0 else (stamp_s - t0) / (t1 - t0)
            return interpolate(self._pose_of_scan(k - 1), self._pose_of_scan(k), f)

    def correction(self, stamp_s: float, pose_used: Pose2 | tuple[float, float, float]) -> NDArray[np.float64]:
        """(4, 4) ``T_new_old``: carries map contents placed at ``stamp_s`` with the map pose
        ``pose_used`` (x, y, yaw) to where the current estimate puts them (identity when
        nothing moved). Apply to points, footprints and object poses in the map frame."""
        new = self.pose_at(stamp_s)
        return matrix4(compose(new, inverse(np.asarray(pose_used, dtype=np.float64))))

    def submaps(self) -> list[SubmapView]:
        """Every submap with its current map-frame pose."""
        with self.global_._lock:
            out = []
            for s in self.local.submaps.all:
                pose = self.global_.submap_global.get(s.index)
                if pose is None:
                    pose = self.global_.to_global(s.local_pose)
                out.append(SubmapView(s.index, pose.copy(), s.grid, s.finished, s.n_scans))
            return out

    @property
    def loop_closures(self) -> int:
        """Number of loop-closure constraints found so far."""
        return len(self.global_.loop_closures)

    def drain(self, timeout_s: float | None = None) -> bool:
        """Wait for queued loop-closure searches (offline runs, tests); False on timeout."""
        return self.global_.drain(timeout_s)

    def optimize(self) -> None:
        """Run a final pose-graph optimisation now (e.g. at the end of an offline run)."""
        self.global_.optimize()

    def rebuild_grid(self, spec: GridSpec) -> ProbabilityGrid:
        """A fresh probability grid over ``spec`` from every node's scan at its optimised pose
        (the global map after re-anchoring)."""
        grid = ProbabilityGrid(spec, self.tables, fixed_size=True)
        with self.global_._lock:
            nodes = list(self.global_.nodes)
            poses = [n.global_pose.copy() for n in nodes]
        for n, p in zip(nodes, poses, strict=True):
            r = transform_scan(p, n.scan)
            grid.insert_scan(r.origin_xy_m, r.near_xy_m, r.far_xy_m, r.hit_xy_m, r.is_hit, r.valid)
        return grid
