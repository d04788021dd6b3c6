"""The service's localization stage: the camera's frames re-posed by the 2D SLAM.

Without GPS the autopilot's position drifts, and a map built with it puts objects in the
wrong cells. With ``service.localization: slam`` every frame passes through
:class:`Localizer` on its way from the camera to perception:

* the altitude-band scan is extracted from the depth (the band the occupancy grid uses) in
  the gravity-aligned body frame, roll and pitch taken from the frame's pose (the
  autopilot's attitude, which does not drift);
* :class:`semmap.slam.Slam2D` matches it with the autopilot's odometry as the motion prior
  (loop closure runs on its own background thread and never blocks this step). The prior is
  the frame's dead-reckoned odometry (``Frame.T_odom_body``: velocity and yaw rate
  integrated), not the autopilot's position estimate: that estimate fuses the poses this
  stage sends it, so its increments would hand the SLAM's own corrections back to it as
  motion (see :meth:`Localizer.odometry_prior`);
* the frame leaves with ``T_map_camera`` built from the SLAM's x, y, yaw, the autopilot's
  roll and pitch, and its height corrected by the floor the depth shows: the map frame is the
  autopilot's frame at the first scan.

Degenerate scans (a corridor, a blank wall) fall back to odometry for the direction they do
not constrain or entirely (``SlamStatus``); that is counted and reported, not silent, and
such a pose is not sent to PX4 as vision (:mod:`companion.service.position_source`).

The stage runs where the camera is read: :class:`LocalizedFrameSource` wraps the frame source,
so the SLAM runs in the camera's reader thread of the perception process, never on the
event loop. Its output reaches the service process through :class:`SharedLocalization`
(shared memory, picklable into a ``spawn`` child): the external-vision stream to PX4
(:class:`companion.mavlink.vision.VisionStream`) and the status read it there.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from companion.service.perception_worker import semantic_map_settings
from companion.shared_record import SharedRecord
from companion.sources.base import FrameSource, WrappedSource
from semmap.costmap import VerticalBand
from semmap.floor import view_floor_height_m
from semmap.frames import invert, pose_from_xyz_rpy, rpy_from_rotation
from semmap.slam import Slam2D, SlamStatus, level_scan_from_depth
from semmap.slam.pose2d import compose, from_matrix4, inverse, relative
from semmap.slam.scan2d import T_level_camera
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: Time constant of the height correction (seconds): PX4's height error drifts over seconds,
#: while each view's floor is a few millimetres off on its own, and a band that jitters from
#: scan to scan gives the matcher inconsistent slices.
FLOOR_OFFSET_TAU_S = 0.5

#: Status codes in the shared array.
_STATUS_CODES = {None: 0.0, SlamStatus.OK: 1.0, SlamStatus.PARTIAL_ODOMETRY: 2.0,
                 SlamStatus.DEGENERATE_FALLBACK_ODOMETRY: 3.0, SlamStatus.ODOMETRY: 4.0}
_STATUS_NAMES = {int(v): (k.value if k is not None else "none") for k, v in _STATUS_CODES.items()}
#: Shared array layout.
_FIELDS = ("seq", "stamp_s", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad", "status",
           "scans", "ok", "partial", "fallbacks", "consecutive_fallbacks", "loop_closures",
           "generation", "loop_searches_dropped", "localize_ms", "resets", "published_monotonic_s",
           "since_match_m", "prior_odometry", "odometry_scale_error", "odometry_heading_drift_rad_s")
_IX = {name: i for i, name in enumerate(_FIELDS)}


@dataclass(frozen=True)
class LocalizationState:
    """The latest localization: ``stamp_s`` of the frame (the camera's clock), its map-frame
    body pose ``T_map_body`` (4, 4), how it was obtained (``status``: a
    :class:`SlamStatus` value) and the counters (see :class:`semmap.slam.SlamStats`).
    ``age_s``: seconds since it was published (monotonic clock)."""

    seq: int
    stamp_s: float
    T_map_body: NDArray[np.float64]  # (4, 4)
    status: str
    scans: int
    ok: int
    partial: int
    fallbacks: int
    consecutive_fallbacks: int
    loop_closures: int
    generation: int
    loop_searches_dropped: int
    localize_ms: float
    age_s: float
    #: Jumps of the matched pose (loop closures, relocalisations; see :class:`JumpCounter`).
    resets: int = 0
    #: Metres the motion prior moved since the last fully matched scan (0 on a full match).
    since_match_m: float = 0.0
    #: True when the motion prior is the frames' own odometry, not the autopilot's estimate.
    prior_is_odometry: bool = False
    #: The motion prior's errors as the SLAM measures and removes them (see :class:`semmap.slam.SlamStats`).
    odometry_scale_error: float = 0.0
    odometry_heading_drift_rad_s: float = 0.0

    @property
    def matched(self) -> bool:
        """True when the latest pose came (at least in part) from scan matching."""
        return self.status in (SlamStatus.OK.value, SlamStatus.PARTIAL_ODOMETRY.value)

    def summary(self) -> dict[str, float | int | str]:
        """The counters as a flat dict for status messages."""
        return {"status": self.status, "scans": self.scans, "ok": self.ok, "partial": self.partial,
                "fallbacks": self.fallbacks, "consecutive_fallbacks": self.consecutive_fallbacks,
                "loop_closures": self.loop_closures, "generation": self.generation, "resets": self.resets,
                "localize_ms": round(self.localize_ms, 2),
                "odometry_scale_error": round(self.odometry_scale_error, 4),
                "odometry_heading_drift_deg_s": round(math.degrees(self.odometry_heading_drift_rad_s), 3)}


class SharedLocalization:
    """The latest localization in shared memory: written by :class:`Localizer` (in the
    perception process), read by the service (vision stream, status). Picklable into a
    ``spawn`` child while it starts."""

    def __init__(self) -> None:
        # One writer (the perception process of the moment); the service reads without waiting.
        self._record = SharedRecord(len(_FIELDS))

    def publish(self, values: dict[str, float]) -> None:
        """Write one update (``seq`` is incremented here)."""
        row = self._record.writer_view().copy()
        for k, v in values.items():
            row[_IX[k]] = float(v)
        row[_IX["seq"]] += 1.0
        row[_IX["published_monotonic_s"]] = time.monotonic()
        self._record.write(row)

    def latest(self) -> LocalizationState | None:
        """The latest update, None before the first (or while it cannot be read whole)."""
        row = self._record.read()
        if row is None:
            return None
        if row[_IX["seq"]] <= 0.0:
            return None
        g = row.__getitem__
        T = pose_from_xyz_rpy(g(_IX["x_m"]), g(_IX["y_m"]), g(_IX["z_m"]), g(_IX["roll_rad"]),
                              g(_IX["pitch_rad"]), g(_IX["yaw_rad"]))
        return LocalizationState(
            int(g(_IX["seq"])), g(_IX["stamp_s"]), T, _STATUS_NAMES.get(int(g(_IX["status"])), "none"),
            int(g(_IX["scans"])), int(g(_IX["ok"])), int(g(_IX["partial"])), int(g(_IX["fallbacks"])),
            int(g(_IX["consecutive_fallbacks"])), int(g(_IX["loop_closures"])), int(g(_IX["generation"])),
            int(g(_IX["loop_searches_dropped"])), g(_IX["localize_ms"]),
            time.monotonic() - g(_IX["published_monotonic_s"]), int(g(_IX["resets"])),
            g(_IX["since_match_m"]), g(_IX["prior_odometry"]) > 0.5, g(_IX["odometry_scale_error"]),
            g(_IX["odometry_heading_drift_rad_s"]))


#: The GIL switch interval of the process the SLAM runs in (seconds).
SLAM_SWITCH_INTERVAL_S = 0.0005
class JumpCounter:
    """Counts the jumps of the matched SLAM pose: a pose farther than ``jump_m`` (or turned
    more than ``jump_rad``) from where the previous matched pose and the odometry since then
    put it. Scan matching corrects by centimetres; a loop closure or a relocalisation after
    fallbacks moves the pose at once, and EKF2 must reset to it (``reset_counter``)."""

    def __init__(self, jump_m: float, jump_rad: float) -> None:
        self.jump_m = jump_m
        self.jump_rad = jump_rad
        self.count = 0
        self._prev: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def update(self, pose_map: NDArray[np.float64], pose_odom: NDArray[np.float64], matched: bool) -> int:
        """The count after one scan's ``pose_map`` and odometry prior ``pose_odom`` (3,) x, y,
        yaw; only matched poses are compared (and remembered)."""
        if not matched:
            return self.count
        pose_map = np.asarray(pose_map, dtype=np.float64).copy()
        pose_odom = np.asarray(pose_odom, dtype=np.float64).copy()
        if self._prev is not None:
            predicted = compose(self._prev[0], relative(self._prev[1], pose_odom))
            d = relative(predicted, pose_map)
            dist, dyaw = math.hypot(float(d[0]), float(d[1])), abs(float(d[2]))
            if dist > self.jump_m or dyaw > self.jump_rad:
                self.count += 1
                log.info("SLAM pose jumped %.2f m, %.1f deg from its prediction: external-vision reset %d",
                         dist, math.degrees(dyaw), self.count)
        self._prev = (pose_map, pose_odom)
        return self.count


def slam_band(cfg: CompanionConfig) -> VerticalBand:
    """The band the SLAM scans: the occupancy grid's scan band (``map.scan_band_m`` or the
    flight band)."""
    return semantic_map_settings(cfg).scan_band


class Localizer:
    """Per-frame SLAM for the service (one caller: the camera's reader thread).

    ``shared``: where each result is published (None = not published). Use :meth:`close`
    to stop the loop-closure thread."""

    def __init__(self, cfg: CompanionConfig, intrinsics: CameraIntrinsics,
                 shared: SharedLocalization | None = None) -> None:
        self.cfg = cfg
        self.intrinsics = intrinsics
        self.shared = shared
        self.T_body_camera = cfg.camera.extrinsics.T_body_camera()
        self.T_camera_body = invert(self.T_body_camera)
        self.band = slam_band(cfg)
        self.slam = Slam2D.from_config(cfg.slam)
        self.last_status: SlamStatus | None = None
        #: Where the motion prior comes from: "odometry" (the frame's dead-reckoned
        #: T_odom_body), "estimate" (the autopilot's pose: frames without odometry), None yet.
        self.prior_source: str | None = None
        self._prior_anchor = np.zeros(3)
        self._last_prior: NDArray[np.float64] | None = None
        self.jumps = JumpCounter(cfg.link.vision_reset_jump_m, math.radians(cfg.link.vision_reset_jump_deg))
        #: The motion prior at the last fully matched scan (None before the first).
        self._prior_at_match: NDArray[np.float64] | None = None
        #: Where the depth's floor lies in the frame the autopilot's height makes (metres): that
        #: height's error, followed over the views that show the floor (``FLOOR_OFFSET_TAU_S``).
        self.floor_offset_m = 0.0
        self._floor_stamp_s: float | None = None

    def since_match_m(self, prior: NDArray[np.float64], status: SlamStatus) -> float:
        """Metres the motion ``prior`` moved since the last fully matched scan: how far the
        directions a partly matched scan could not see were carried by odometry alone."""
        if status is SlamStatus.OK or self._prior_at_match is None:
            self._prior_at_match = np.asarray(prior, dtype=np.float64).copy()
            return 0.0
        return float(math.hypot(prior[0] - self._prior_at_match[0], prior[1] - self._prior_at_match[1]))

    def height_above_floor_m(self, depth: NDArray[np.floating], roll: float, pitch: float, z: float,
                             stamp_s: float) -> float:
        """The body's height above the floor: the autopilot's ``z`` corrected by where the depth
        shows the floor. The SLAM's scan and the map's grid are slices of the room by height,
        and perception measures objects only in views whose floor lies near where the pose puts
        it, while an autopilot's height on range finder and baro is decimetres off (see
        docs/mavlink.md)."""
        floor_m = view_floor_height_m(depth, self.intrinsics, T_level_camera(self.T_body_camera, roll, pitch, z),
                                      (self.cfg.camera.depth_min_m, self.cfg.camera.depth_max_m),
                                      prior_height_m=self.floor_offset_m)
        if floor_m is not None:
            if self._floor_stamp_s is None:
                self.floor_offset_m = floor_m
            else:
                gain = 1.0 - math.exp(-max(0.0, stamp_s - self._floor_stamp_s) / FLOOR_OFFSET_TAU_S)
                self.floor_offset_m += gain * (floor_m - self.floor_offset_m)
            self._floor_stamp_s = stamp_s
        return z - self.floor_offset_m

    def close(self) -> None:
        """Stop the background loop closer."""
        self.slam.close()

    def odometry_prior(self, frame: Frame, estimate_xy_yaw: tuple[float, float, float]) -> NDArray[np.float64]:
        """The odometry pose (3,) x_m, y_m, yaw_rad handed to the SLAM with ``frame``'s scan:
        the SLAM predicts each scan's pose by composing its previous pose with the
        increment of this pose since the previous scan.

        It is the frame's dead-reckoned odometry (``T_odom_body``) when it has one, else the
        autopilot's estimate ``estimate_xy_yaw`` (from ``T_map_camera``). The estimate is the
        fallback only: PX4 fuses the SLAM poses this stage sends as external vision, so the
        estimate's increment between two frames holds, beside the motion, the part of the
        SLAM's latest correction PX4 took in, and the SLAM would apply that correction
        twice. While the scans constrain the pose weakly (turning on the spot, few hits) the
        two then chase each other off the truth (tests/integration/test_service_slam.py
        flies it).

        The odometry frame is anchored to the map frame by the fixed offset that puts its
        first pose on the estimate (the map frame is the autopilot's frame at the first scan).
        Should the source change (a frame without odometry), the new one is anchored on the
        last pose handed over, so the prior stays continuous."""
        T = frame.T_odom_body
        if T is not None and np.all(np.isfinite(T)):
            raw = from_matrix4(T)
            source = "odometry"
        else:
            raw = np.asarray(estimate_xy_yaw, dtype=np.float64)
            source = "estimate"
        if source != self.prior_source:
            on = np.asarray(estimate_xy_yaw, dtype=np.float64) if self._last_prior is None else self._last_prior
            self._prior_anchor = compose(on, inverse(raw))
            log.log(logging.INFO if self.prior_source is None else logging.WARNING,
                    "SLAM motion prior: the %s%s", "frames' dead-reckoned odometry" if source == "odometry"
                    else "autopilot's position estimate (the frames carry no odometry)",
                    "" if self.prior_source is None else f" from frame {frame.index} on (was the {self.prior_source})")
            self.prior_source = source
        self._last_prior = compose(self._prior_anchor, raw)
        return self._last_prior.copy()

    def localize(self, frame: Frame) -> Frame:
        """``frame`` with ``T_map_camera`` from the SLAM pose. Its incoming ``T_map_camera`` is
        the autopilot's pose (odometry frame); a frame without a (finite) pose is returned
        unchanged for perception to skip or reject."""
        if frame.T_map_camera is None or not np.all(np.isfinite(frame.T_map_camera)):
            return frame
        t0 = time.perf_counter()
        T_odom_body = np.asarray(frame.T_map_camera, dtype=np.float64) @ self.T_camera_body
        roll, pitch, yaw = rpy_from_rotation(T_odom_body[:3, :3])
        x, y, z_autopilot = (float(v) for v in T_odom_body[:3, 3])
        depth = np.asarray(frame.depth_m)
        z = self.height_above_floor_m(depth, roll, pitch, z_autopilot, frame.stamp_s)
        scan = level_scan_from_depth(depth, self.intrinsics, self.T_body_camera, roll, pitch, z, self.band,
                                     min_depth_m=self.cfg.camera.depth_min_m,
                                     max_depth_m=self.cfg.camera.depth_max_m,
                                     stride_px=2 if depth.shape[1] > 200 else 1, stamp_s=frame.stamp_s)
        # Slam2D locks its own state against the loop-closure thread.
        prior = self.odometry_prior(frame, (x, y, yaw))
        est = self.slam.add_scan(frame.stamp_s, scan, prior)
        resets = self.jumps.update(est.pose_map, prior, est.status is SlamStatus.OK)
        since_match_m = self.since_match_m(prior, est.status)
        stats = self.slam.stats()
        self.last_status = est.status
        px, py, pyaw = (float(v) for v in est.pose_map)
        T_map_body = pose_from_xyz_rpy(px, py, z, roll, pitch, pyaw)
        ms = 1e3 * (time.perf_counter() - t0)
        if self.shared is not None:
            self.shared.publish({
                "stamp_s": frame.stamp_s, "x_m": px, "y_m": py, "z_m": z, "roll_rad": roll,
                "pitch_rad": pitch, "yaw_rad": pyaw, "status": _STATUS_CODES[est.status],
                "scans": stats.scans, "ok": stats.ok, "partial": stats.partial, "fallbacks": stats.fallbacks,
                "consecutive_fallbacks": stats.consecutive_fallbacks, "loop_closures": stats.loop_closures,
                "generation": stats.generation, "loop_searches_dropped": stats.loop_searches_dropped,
                "localize_ms": ms, "resets": resets, "since_match_m": since_match_m,
                "prior_odometry": 1.0 if self.prior_source == "odometry" else 0.0,
                "odometry_scale_error": stats.odometry_scale_error,
                "odometry_heading_drift_rad_s": stats.odometry_heading_drift_rad_s})
        return replace(frame, T_map_camera=T_map_body @ self.T_body_camera)


class LocalizedFrameSource(WrappedSource):
    """``inner``'s frames re-posed by a :class:`Localizer` (built on open, in whichever
    process reads the camera; picklable before that)."""

    def __init__(self, inner: FrameSource, cfg: CompanionConfig, shared: SharedLocalization | None = None) -> None:
        super().__init__(inner)
        self.cfg = cfg
        self.shared = shared
        self._localizer: Localizer | None = None
        self._priority_set = False

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_localizer": None}

    @property
    def localizer(self) -> Localizer:
        """The SLAM stage (created on first use)."""
        if self._localizer is None:
            self._localizer = Localizer(self.cfg, self.inner.intrinsics, self.shared)
            log.info("localization: SLAM on the camera's frames")
        return self._localizer

    def open(self) -> None:
        self.inner.open()
        _ = self.localizer
        # The SLAM's many short numpy calls each give the GIL up; detection's Python in the
        # same process would keep it the default 5 ms every time, so hand it over sooner.
        sys.setswitchinterval(SLAM_SWITCH_INTERVAL_S)

    def close(self) -> None:
        try:
            self.inner.close()
        finally:
            if self._localizer is not None:
                self._localizer.close()
                s = self._localizer.slam.stats()
                log.info("localization: %d scans, %d matched, %d partly and %d wholly from odometry, "
                         "%d loop closures", s.scans, s.ok, s.partial, s.fallbacks, s.loop_closures)
                self._localizer = None

    def read(self) -> Frame | None:
        if not self._priority_set:
            self._priority_set = True
            reader_thread_at_parent_priority()
        frame = self.inner.read()
        if frame is None:
            return None
        return self.localizer.localize(frame)


def reader_thread_at_parent_priority() -> None:
    """Give the calling thread (the camera's reader, which runs the SLAM) the scheduling
    priority of the process that started this one: the perception process is niced so that
    detection yields to the service, but the SLAM pose is PX4's only position without GPS
    and must not yield with it. Needs CAP_SYS_NICE (or RLIMIT_NICE) to undo a nice; without
    it the thread keeps the process's priority and a warning says so."""
    try:
        parent = os.getpriority(os.PRIO_PROCESS, os.getppid())
        tid = threading.get_native_id()
        if os.getpriority(os.PRIO_PROCESS, tid) > parent:
            os.setpriority(os.PRIO_PROCESS, tid, parent)
    except OSError as exc:
        log.warning("localization: the SLAM thread keeps the perception process's lower priority (%s); "
                    "grant CAP_SYS_NICE or LimitNICE so it runs at the service's", exc)


def localized_source(cfg: CompanionConfig, source: FrameSource,
                     shared: SharedLocalization | None = None) -> FrameSource:
    """``source`` wrapped in the localization stage when ``service.localization`` is
    ``slam``, else ``source`` itself (frames keep the autopilot's pose)."""
    if cfg.service.localization != "slam":
        return source
    return LocalizedFrameSource(source, cfg, shared)
