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
* the frame leaves with ``T_map_camera`` built from the SLAM's x, y, yaw and the autopilot's
  height, roll and pitch: the map frame is the autopilot's frame at the first scan.

Degenerate scans (a corridor, a blank wall) fall back to odometry for the direction they do
not constrain or entirely (``SlamStatus``); that is counted and reported, not silent, and
such a pose is not sent to PX4 as vision (:func:`vision_pose`).
``slam.mode: odometry`` keeps the stage but trusts the autopilot.

The stage runs where the camera is read: :class:`LocalizedFrameSource` wraps the frame source,
so the SLAM runs in the camera's reader thread of the perception process, never on the
event loop. Its output reaches the service process through :class:`SharedLocalization`
(shared memory, picklable into a ``spawn`` child): the external-vision stream to PX4
(:class:`companion.mavlink.vision.VisionStream`) and the status read it there.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from companion.mavlink.link import MavlinkLink
from companion.mavlink.vision import VisionPose, VisionStream
from companion.service.perception_worker import semantic_map_settings
from companion.shared_record import SharedRecord
from companion.sources.base import FrameSource, WrappedSource
from semmap.costmap import VerticalBand
from semmap.errors import ConfigError
from semmap.frames import invert, pose_from_xyz_rpy, rpy_from_rotation
from semmap.slam import Slam2D, SlamStatus, level_scan_from_depth
from semmap.slam.pose2d import compose, inverse
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: Status codes in the shared array.
_STATUS_CODES = {None: 0.0, SlamStatus.OK: 1.0, SlamStatus.PARTIAL_ODOMETRY: 2.0,
                 SlamStatus.DEGENERATE_FALLBACK_ODOMETRY: 3.0, SlamStatus.ODOMETRY: 4.0}
_STATUS_NAMES = {int(v): (k.value if k is not None else "none") for k, v in _STATUS_CODES.items()}
#: Shared array layout.
_FIELDS = ("seq", "stamp_s", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad", "status",
           "scans", "ok", "partial", "fallbacks", "consecutive_fallbacks", "loop_closures",
           "generation", "loop_searches_dropped", "localize_ms", "published_monotonic_s")
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

    @property
    def matched(self) -> bool:
        """True when the latest pose came (at least in part) from scan matching."""
        return self.status in (SlamStatus.OK.value, SlamStatus.PARTIAL_ODOMETRY.value)

    def summary(self) -> dict[str, float | int | str]:
        """The counters as a flat dict for status messages."""
        return {"status": self.status, "scans": self.scans, "ok": self.ok, "partial": self.partial,
                "fallbacks": self.fallbacks, "consecutive_fallbacks": self.consecutive_fallbacks,
                "loop_closures": self.loop_closures, "generation": self.generation,
                "localize_ms": round(self.localize_ms, 2)}


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
            time.monotonic() - g(_IX["published_monotonic_s"]))


#: A SLAM pose older than this is not sent to the autopilot (the camera stalled).
VISION_MAX_AGE_S = 1.0
#: External-vision message rate (PX4 expects 30 Hz or more from a VIO).
VISION_RATE_HZ = 30.0


def vision_pose(shared: SharedLocalization, max_age_s: float = VISION_MAX_AGE_S) -> VisionPose | None:
    """The latest SLAM pose for the autopilot's external-vision input, or None when there is
    none, it is stale, or it was not matched in full (PX4 keeps its own estimate then).

    Why not a partly matched pose: along its unconstrained direction it is the previous SLAM
    pose moved by the increment of PX4's estimate, and that estimate is what the earlier
    vision poses corrected. Fed back, the direction closes a loop with no measurement in it:
    each fusion pulls the estimate a fraction of the way to the SLAM pose, the next scan's
    prediction moves the SLAM pose by that same pull, and both drift together at that
    fraction of their offset per scan (test_service_slam: a 4.5 cm offset became 0.26 m in
    eleven partly matched scans along a wall; the map then kept it). An odometry fallback
    is not sent for the same reason."""
    st = shared.latest()
    if st is None or st.status != SlamStatus.OK.value or st.age_s > max_age_s:
        return None
    return VisionPose(st.stamp_s, st.T_map_body, 100, st.generation & 0xFF)


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
        two then chase each other off the truth. Measured on the SLAM integration test's
        flight (tests/integration/test_service_slam.py): live error p95 0.13-0.27 m over 11
        runs with the estimate's increments, 0.065-0.098 m over 8 with the odometry's.

        The odometry frame is anchored to the map frame by the fixed offset that puts its
        first pose on the estimate (the map frame is the autopilot's frame at the first scan).
        Should the source change (a frame without odometry), the new one is anchored on the
        last pose handed over, so the prior stays continuous."""
        T = frame.T_odom_body
        if T is not None and np.all(np.isfinite(T)):
            raw = np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])], dtype=np.float64)
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
        x, y, z = (float(v) for v in T_odom_body[:3, 3])
        depth = np.asarray(frame.depth_m)
        scan = level_scan_from_depth(depth, self.intrinsics, self.T_body_camera, roll, pitch, z, self.band,
                                     min_depth_m=self.cfg.camera.depth_min_m,
                                     max_depth_m=self.cfg.camera.depth_max_m,
                                     stride_px=2 if depth.shape[1] > 200 else 1, stamp_s=frame.stamp_s)
        # Slam2D locks its own state against the loop-closure thread.
        est = self.slam.add_scan(frame.stamp_s, scan, self.odometry_prior(frame, (x, y, yaw)))
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
                "localize_ms": ms})
        return replace(frame, T_map_camera=T_map_body @ self.T_body_camera)


class LocalizedFrameSource(WrappedSource):
    """``inner``'s frames re-posed by a :class:`Localizer` (built on open, in whichever
    process reads the camera; picklable before that)."""

    def __init__(self, inner: FrameSource, cfg: CompanionConfig, shared: SharedLocalization | None = None) -> None:
        super().__init__(inner)
        self.cfg = cfg
        self.shared = shared
        self._localizer: Localizer | None = None

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_localizer": None}

    @property
    def localizer(self) -> Localizer:
        """The SLAM stage (created on first use)."""
        if self._localizer is None:
            self._localizer = Localizer(self.cfg, self.inner.intrinsics, self.shared)
            log.info("localization: SLAM (%s mode) on the camera's frames", self.cfg.slam.mode)
        return self._localizer

    def open(self) -> None:
        self.inner.open()
        _ = self.localizer

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
        frame = self.inner.read()
        if frame is None:
            return None
        return self.localizer.localize(frame)


def localized_source(cfg: CompanionConfig, source: FrameSource,
                     shared: SharedLocalization | None = None) -> FrameSource:
    """``source`` wrapped in the localization stage when ``service.localization`` is
    ``slam``, else ``source`` itself (frames keep the autopilot's pose)."""
    if cfg.service.localization != "slam":
        return source
    return LocalizedFrameSource(source, cfg, shared)


class ServiceLocalization:
    """The localization stage as the service wires it: the shared state, the camera wrapped
    in the SLAM (:meth:`source`), the external-vision stream to PX4 (:meth:`vision_stream`)
    and what the status reports (:meth:`health`, :meth:`detail`, :meth:`summary`).

    With ``service.localization: slam`` the map is in the SLAM's frame; the planner flies
    with the autopilot's position, which is in that frame only when PX4 fuses the SLAM pose,
    so ``link.external_vision`` must be on (a :class:`ConfigError` otherwise)."""

    #: A run of consecutive odometry fallbacks this long marks localization unhealthy.
    UNHEALTHY_FALLBACK_RUN = 30

    def __init__(self, cfg: CompanionConfig) -> None:
        self.cfg = cfg
        self.enabled = cfg.service.localization == "slam"
        if self.enabled and not cfg.link.external_vision:
            raise ConfigError("service.localization is 'slam' but link.external_vision is false: the map would be "
                              "in the SLAM's frame and the setpoints in the autopilot's drifting one; set "
                              "link.external_vision: true (PX4 then fuses the SLAM pose)")
        self.shared = SharedLocalization() if self.enabled else None
        self.stream: VisionStream | None = None

    def source(self, frame_source: FrameSource) -> FrameSource:
        """The camera as perception should read it (wrapped in the SLAM when enabled)."""
        return localized_source(self.cfg, frame_source, self.shared)

    def vision_stream(self, link: MavlinkLink) -> contextlib.AbstractAsyncContextManager[object]:
        """The 30 Hz external-vision stream on ``link`` (a no-op when disabled)."""
        shared = self.shared
        if shared is None or not self.cfg.link.external_vision:
            return contextlib.nullcontext()
        self.stream = VisionStream(link, lambda: vision_pose(shared), VISION_RATE_HZ)
        return self.stream

    def latest(self) -> LocalizationState | None:
        """The latest SLAM result (None when disabled or before the first frame)."""
        return self.shared.latest() if self.shared is not None else None

    def health(self) -> dict[str, bool]:
        """``{"localization": ok}`` for the status (empty when disabled): False before the
        first scan, when the last one is older than the camera allows, or in a long run
        of odometry fallbacks."""
        if not self.enabled:
            return {}
        st = self.latest()
        ok = (st is not None and st.age_s <= self.cfg.map.stale_after_s
              and st.consecutive_fallbacks < self.UNHEALTHY_FALLBACK_RUN)
        return {"localization": ok}

    def detail(self) -> str:
        """A short status text (empty when disabled)."""
        if not self.enabled:
            return ""
        st = self.latest()
        if st is None:
            return "slam: no scan yet"
        sent = self.stream.sent if self.stream is not None else 0
        return (f"slam {st.status}: {st.scans} scans, {st.partial} partly / {st.fallbacks} wholly from "
                f"odometry, {st.loop_closures} loops, {sent} vision msgs")

    def summary(self) -> dict[str, float | int | str]:
        """The counters for the run's report (empty when disabled)."""
        st = self.latest()
        if st is None:
            return {}
        out = st.summary()
        if self.stream is not None:
            out["vision_sent"] = self.stream.sent
        return out
