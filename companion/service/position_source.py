"""The service's side of localization: the SLAM pose as PX4's external vision.

:class:`ServiceLocalization` wires the stage of :mod:`companion.service.localization` (which
runs in the perception process) into the service: the shared state, the 30 Hz
external-vision stream with PX4's TIMESYNC brought to convergence, the vision-loss guard and
what the status reports. :class:`VisionPoseSource` decides which SLAM poses PX4 may fuse.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable

from companion.background import BackgroundTasks
from companion.config import CompanionConfig
from companion.mavlink.commands import CommandSender
from companion.mavlink.link import MavlinkLink
from companion.mavlink.params import ParamWatch
from companion.mavlink.timesync import TimesyncConvergence
from companion.mavlink.vision import DEFAULT_YAW_STD_RAD, VisionPose, VisionStream
from companion.service.localization import LocalizationState, SharedLocalization, localized_source
from companion.service.vision_loss import (
    FLOW_PARAM,
    LAND_SPEED_PARAM,
    NOAID_PARAM,
    VisionLossGuard,
    VisionLossMonitor,
)
from companion.sources.base import FrameSource
from semmap.errors import ConfigError
from semmap.slam import SlamStatus

log = logging.getLogger(__name__)

#: A SLAM pose older than this is not sent to the autopilot (the camera stalled).
VISION_MAX_AGE_S = 1.0
#: EKF2 fuses a pose only while its delayed horizon (``EKF2_DELAY_MAX``, 200 ms by default,
#: behind now) is less than 100 ms past the pose's stamp (its buffer's ``pop_first_older_than``):
#: a pose older than this at sending is dropped there, so it does not count as sent here.
FUSION_WINDOW_S = 0.3
#: External-vision message rate (PX4 expects 30 Hz or more from a VIO).
VISION_RATE_HZ = 30.0
#: A pose carried by odometry whose grown 1-sigma exceeds this is not sent: beyond it the
#: pose could no longer keep the planner's clearance from what it flies past.
PARTIAL_MAX_STD_M = 0.25
#: The statuses whose pose (some or all of it) the SLAM carried on its odometry prior.
_DEAD_RECKONED = (SlamStatus.PARTIAL_ODOMETRY.value, SlamStatus.DEGENERATE_FALLBACK_ODOMETRY.value)


class VisionPoseSource:
    """The latest SLAM pose for the autopilot's external-vision input (the
    :class:`VisionStream`'s source, called at its rate): None when there is none, it is
    stale, or it was not matched in full (PX4 keeps its own estimate then). Each pose carries
    the configured 1-sigma errors and a ``reset_counter`` that counts the SLAM's jumps (see
    :class:`JumpCounter`) and every return after a gap of ``reset_after_gap_s`` or more:
    PX4 dead-reckoned on its IMU meanwhile and would reject the pose at its innovation gate.

    Why not a partly matched pose: along its unconstrained direction it is the previous SLAM
    pose moved by the increment of PX4's estimate, and that estimate is what the earlier
    vision poses corrected. Fed back, the direction closes a loop with no measurement in it:
    each fusion pulls the estimate a fraction of the way to the SLAM pose, the next scan's
    prediction moves the SLAM pose by that same pull, and both drift together at that
    fraction of their offset per scan (test_service_slam: a 4.5 cm offset became 0.26 m in
    eleven partly matched scans along a wall; the map then kept it). An odometry fallback
    is not sent for the same reason.

    That loop needs the prior to be PX4's estimate. With ``odometry_independent`` (the
    frames' odometry is a sensor of the vehicle's own, see
    ``link.vision_odometry_independent``) a partly matched pose built on that odometry is
    sent, and so is a scan that matched nothing (the pose then is the last match moved by
    that odometry, as a VIO coasts), its position 1-sigma grown by ``odometry_drift_per_m``
    per metre since the last full match, up to :data:`PARTIAL_MAX_STD_M`: a wall that hides
    one direction for a few seconds then costs EKF2 some confidence, not its only position
    source. A camera that delivers nothing still stops the stream (the pose goes stale)."""

    def __init__(self, shared: SharedLocalization, *, max_age_s: float = 1.0, position_std_m: float | None = None,
                 yaw_std_rad: float | None = None, reset_after_gap_s: float = math.inf,
                 odometry_independent: bool = False, odometry_drift_per_m: float = 0.05,
                 fusion_window_s: float = math.inf, clock: Callable[[], float] = time.monotonic) -> None:
        self.shared = shared
        self.max_age_s = max_age_s
        self.position_std_m = position_std_m
        self.yaw_std_rad = yaw_std_rad
        self.reset_after_gap_s = reset_after_gap_s
        self.odometry_independent = odometry_independent
        self.odometry_drift_per_m = odometry_drift_per_m
        self.fusion_window_s = fusion_window_s
        #: Poses held back because they were captured too long ago for EKF2 to fuse.
        self.too_late = 0
        self.clock = clock
        #: Times a partly matched pose was handed out (with a grown covariance).
        self.partial_sends = 0
        #: Returns after a gap (each bumped the reset counter).
        self.gap_resets = 0
        self._last_given_s: float | None = None

    @classmethod
    def from_config(cls, shared: SharedLocalization, cfg: CompanionConfig) -> VisionPoseSource:
        link = cfg.link
        return cls(shared, max_age_s=VISION_MAX_AGE_S, position_std_m=link.vision_position_std_m,
                   yaw_std_rad=math.radians(link.vision_yaw_std_deg), reset_after_gap_s=link.vision_lost_hold_s,
                   odometry_independent=link.vision_odometry_independent,
                   odometry_drift_per_m=link.vision_odometry_drift_per_m, fusion_window_s=FUSION_WINDOW_S)

    def dead_reckoned_std(self, st: LocalizationState) -> tuple[float, float | None] | None:
        """The position and yaw 1-sigma (m, rad) a pose that is not fully matched may go to
        PX4 with; None when it may not go. A wholly dead-reckoned pose (the scan saw
        nothing usable) grows its yaw 1-sigma too, by the drift fraction in radians per metre."""
        if not (self.odometry_independent and st.prior_is_odometry and st.status in _DEAD_RECKONED):
            return None
        grown_m = self.odometry_drift_per_m * st.since_match_m
        std = math.hypot(self.position_std_m or 0.0, grown_m)
        if std > PARTIAL_MAX_STD_M:
            return None
        yaw = self.yaw_std_rad
        if st.status == SlamStatus.DEGENERATE_FALLBACK_ODOMETRY.value:
            yaw = math.hypot(yaw if yaw is not None else DEFAULT_YAW_STD_RAD, grown_m)
        return std, yaw

    def __call__(self) -> VisionPose | None:
        st = self.shared.latest()
        if st is None or st.age_s > self.max_age_s:
            return None
        now = self.clock()
        capture_age_s = now - st.stamp_s
        # Only a stamp on our clock can be judged (a camera on another clock: not checked).
        if self.fusion_window_s < capture_age_s <= self.max_age_s:
            self.too_late += 1
            if self.too_late % 30 == 1:
                log.warning("SLAM pose %.0f ms after its capture, past EKF2's fusion window: not sent (%d so far)",
                            1e3 * capture_age_s, self.too_late)
            return None
        std, yaw_std = self.position_std_m, self.yaw_std_rad
        if st.status != SlamStatus.OK.value:
            grown = self.dead_reckoned_std(st)
            if grown is None:
                return None
            std, yaw_std = grown
            self.partial_sends += 1
        if self._last_given_s is not None and now - self._last_given_s >= self.reset_after_gap_s:
            self.gap_resets += 1
            log.warning("external vision back after %.1f s without a matched SLAM pose: reset counter bumped "
                        "(PX4 takes the pose as it is)", now - self._last_given_s)
        self._last_given_s = now
        return VisionPose(st.stamp_s, st.T_map_body, 100, (st.resets + self.gap_resets) & 0xFF,
                          std, yaw_std)


def vision_pose(shared: SharedLocalization, max_age_s: float = VISION_MAX_AGE_S) -> VisionPose | None:
    """One look at the latest SLAM pose for PX4 (see :class:`VisionPoseSource`), without
    covariances or gap tracking."""
    return VisionPoseSource(shared, max_age_s=max_age_s)()


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
        if cfg.sim.gps_denied and cfg.sim.autopilot == "mock" and not (self.enabled and cfg.link.vision_is_position_source):
            raise ConfigError("sim.gps_denied: the mock autopilot's only position source is the SLAM pose; set "
                              "service.localization: slam, link.external_vision: true and "
                              "link.vision_is_position_source: true")
        self.shared = SharedLocalization() if self.enabled else None
        self.stream: VisionStream | None = None
        self.vision_source: VisionPoseSource | None = None
        self.loss_guard_: VisionLossGuard | None = None
        self.timesync: TimesyncConvergence | None = None

    def source(self, frame_source: FrameSource) -> FrameSource:
        """The camera as perception should read it (wrapped in the SLAM when enabled)."""
        return localized_source(self.cfg, frame_source, self.shared)

    def vision_stream(self, link: MavlinkLink) -> contextlib.AbstractAsyncContextManager[object]:
        """The 30 Hz external-vision stream on ``link`` (a no-op when disabled), with PX4's
        TIMESYNC brought to convergence first (:class:`TimesyncConvergence`): until then PX4
        stamps each pose on arrival, a SLAM latency late."""
        shared = self.shared
        if shared is None or not self.cfg.link.external_vision:
            return contextlib.nullcontext()
        self.vision_source = VisionPoseSource.from_config(shared, self.cfg)
        self.stream = VisionStream(link, self.vision_source, VISION_RATE_HZ)
        c = self.cfg.link
        self.timesync = TimesyncConvergence(link, CommandSender(link, c.target_system, c.target_component),
                                            c.target_system)
        return self._vision_stream(self.stream, self.timesync)

    @contextlib.asynccontextmanager
    async def _vision_stream(self, stream: VisionStream, timesync: TimesyncConvergence) -> AsyncIterator[VisionStream]:
        detach = timesync.attach()
        tasks = BackgroundTasks()
        await tasks.open()
        try:
            tasks.start(timesync.run(), name="timesync-convergence")
            async with stream:
                yield stream
        finally:
            await tasks.close()
            detach()

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
            out["vision_sent_new"] = self.stream.sent_new
        if self.vision_source is not None:
            out["vision_gap_resets"] = self.vision_source.gap_resets
        if self.loss_guard_ is not None:
            out["vision_loss_actions"] = ",".join(a.value for _, a, _ in self.loss_guard_.events)
            if self.loss_guard_.flow_aided is not None:
                out["px4_flow_aided"] = int(self.loss_guard_.flow_aided)
        return out

    @property
    def pose_ok(self) -> bool:
        """False while the vehicle holds or lands for want of our pose (see :mod:`.vision_loss`)."""
        return self.loss_guard_ is None or self.loss_guard_.monitor.pose_ok

    def loss_guard(self, link: MavlinkLink, in_air: Callable[[], bool], land: Callable[[], Awaitable[None]],
                   height_m: Callable[[], float | None] | None = None) -> VisionLossGuard | None:
        """The guard that holds and lands when PX4's vision stops (None unless the SLAM pose
        goes to PX4 as its only position source, ``link.vision_is_position_source``). It reads
        PX4's ``EKF2_NOAID_TOUT`` and ``MPC_LAND_SPEED`` to land in time from ``height_m()``
        (above the floor; ``planner.flight_altitude_m`` while unknown)."""
        c = self.cfg.link
        if self.shared is None or not c.external_vision or not c.vision_is_position_source:
            return None
        altitude_m = self.cfg.planner.flight_altitude_m
        monitor = VisionLossMonitor(c.vision_lost_hold_s, c.vision_lost_land_s, default_height_m=altitude_m)
        params = ParamWatch(link, c.target_system, c.target_component, (NOAID_PARAM, LAND_SPEED_PARAM))
        flow = ParamWatch(link, c.target_system, c.target_component, (FLOW_PARAM,))
        self.loss_guard_ = VisionLossGuard(monitor, link, self.vision_age_s, in_air, land, clock=time.monotonic,
                                           height_m=height_m, params=params, flight_altitude_m=altitude_m,
                                           flow_param=flow)
        return self.loss_guard_

    def vision_age_s(self) -> float | None:
        """Seconds since the capture of the last new SLAM pose sent to PX4 (None: never, or
        disabled): EKF2's dead-reckoning timeout runs from the fused pose's time stamp, its
        capture. The stream repeats a pose until the next scan, and a repeat tells EKF2
        nothing. A stamp that is no plausible capture time on our clock counts from the send."""
        stream = self.stream
        if stream is None or stream.last_new_s is None:
            return None
        now = time.monotonic()
        stamp = stream.last_new_stamp_s
        latency = stream.last_new_s - stamp if stamp is not None else math.nan
        return now - stream.last_new_s + (latency if 0.0 <= latency <= VISION_MAX_AGE_S else 0.0)
