"""A live Intel RealSense (D4xx) camera through ``pyrealsense2`` (the ``realsense`` extra).

Colour (RGB8) and depth (Z16) at the same size and rate; depth is aligned to colour with
``rs.align``, so the frame's intrinsics are the colour stream's. The depth scale (metres
per Z16 count) is read from the device. A live camera occasionally times out or delivers an
incomplete frame set: such frames are skipped and counted in ``dropped_frames``; only
``max_consecutive_failures`` failures in a row raise :class:`FrameError` (the camera is gone).

``Frame.stamp_s`` is the capture time on ``time.monotonic()``, the clock the rest of the
service uses (the telemetry poses a frame is posed from are on it too): by the time a frame set
has crossed USB and been aligned it is tens of milliseconds old, a few degrees of yaw on a
turning drone if it were stamped on arrival. :class:`CaptureClock` maps the depth frame's own
timestamp onto ``time.monotonic`` by its clock domain (librealsense's ``rs2_timestamp_domain``):

* ``global_time`` (D4xx default with frame metadata: the device clock mapped by librealsense
  onto the host's system clock) and ``system_time`` (no metadata: the host's system clock when
  the backend received the frame) are wall-clock milliseconds: the frame's age is the wall
  clock now minus that stamp, and the stamp is ``time.monotonic()`` now minus that age. A wall
  clock stepped by NTP moves both readings alike. An age outside ``[-5 ms, max_age_s]`` is not
  believed: that frame is stamped on arrival and counted (``stamps_on_arrival``).
* ``hardware_clock`` (the device's own counter, unrelated to the host): its offset to
  ``time.monotonic`` is the running minimum of arrival minus device time
  (:class:`companion.sources.poses.BootClock`, the autopilot clock's estimator), which removes
  the varying part of the latency and keeps only the smallest seen.

The global time option is switched on where a sensor offers it.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from companion.sources.base import FrameSource
from companion.sources.poses import BootClock
from semmap.errors import FrameError
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)


def _domain_name(domain: Any) -> str:
    """``rs.timestamp_domain.global_time`` -> ``"global_time"``."""
    return str(domain).rsplit(".", 1)[-1].lower()


class CaptureClock:
    """Capture times of RealSense frames on the host's ``time.monotonic`` (module docstring)."""

    WALL_DOMAINS = ("global_time", "system_time")

    def __init__(self, max_age_s: float = 0.5, tolerance_s: float = 0.005) -> None:
        self.max_age_s = max_age_s
        self.tolerance_s = tolerance_s
        self._hardware = BootClock()
        self.stamps_on_arrival = 0

    def capture_stamp_s(self, device_ms: float, domain: str, arrival_monotonic_s: float,
                        arrival_wall_s: float) -> float:
        """The capture time on the monotonic clock of a frame whose device timestamp is
        ``device_ms`` in clock ``domain``, read at ``arrival_monotonic_s`` / ``arrival_wall_s``."""
        if domain in self.WALL_DOMAINS:
            age_s = arrival_wall_s - device_ms * 1e-3
            if -self.tolerance_s <= age_s <= self.max_age_s:
                return arrival_monotonic_s - max(0.0, age_s)
            return self._on_arrival(arrival_monotonic_s, f"{domain} timestamp is {age_s:.3f} s from "
                                    f"the host clock (accepted: -{self.tolerance_s:.3f}..{self.max_age_s:.3f} s)")
        if domain == "hardware_clock":
            return min(arrival_monotonic_s, self._hardware.to_local(device_ms * 1e-3, arrival_monotonic_s))
        return self._on_arrival(arrival_monotonic_s, f"timestamp domain {domain!r} is not a known one")

    def _on_arrival(self, arrival_monotonic_s: float, reason: str) -> float:
        """Stamp a frame on arrival, counted; logged on the first and every 300th."""
        self.stamps_on_arrival += 1
        if self.stamps_on_arrival == 1 or self.stamps_on_arrival % 300 == 0:
            log.warning("RealSense %s: stamped on arrival (%d frames so far)", reason, self.stamps_on_arrival)
        return arrival_monotonic_s


class RealSenseFrameSource(FrameSource):
    """Aligned RGB-D frames of a RealSense camera.

    ``rs_module`` is the ``pyrealsense2`` module (imported on :meth:`open` when None);
    ``pipeline`` an ``rs.pipeline`` (created from the module when None). Tests pass fakes of
    both. ``serial`` selects a device; None takes the first one found.
    """

    def __init__(
        self,
        serial: str | None = None,
        width_px: int = 640,
        height_px: int = 480,
        rate_hz: float = 30.0,
        depth_min_m: float = 0.3,
        depth_max_m: float = 6.0,
        timeout_ms: int = 1000,
        max_consecutive_failures: int = 30,
        rs_module: Any = None,
        pipeline: Any = None,
    ) -> None:
        self.serial = serial
        self.width_px = width_px
        self.height_px = height_px
        self.rate_hz = rate_hz
        self.depth_min_m = depth_min_m
        self.depth_max_m = depth_max_m
        self.timeout_ms = timeout_ms
        self.max_consecutive_failures = max_consecutive_failures
        self._rs = rs_module
        self._pipeline = pipeline
        self._align: Any = None
        self._intrinsics: CameraIntrinsics | None = None
        self.depth_scale_m = 0.001
        self.frames_read = 0
        self.dropped_frames = 0
        self._consecutive_failures = 0
        self._running = False
        self.last_device_stamp_ms = 0.0
        self.last_stamp_domain = ""
        #: Arrival minus capture time of the last frame (what the capture stamp corrected).
        self.last_latency_s = 0.0
        self.capture_clock = CaptureClock()

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The colour stream's intrinsics (depth is aligned to it); starts the camera."""
        self.open()
        assert self._intrinsics is not None
        return self._intrinsics

    def open(self) -> None:
        """Start the pipeline; read the depth scale and the colour intrinsics. Raises
        :class:`FrameError` if the SDK is missing or the device cannot be started."""
        if self._running:
            return
        if self._rs is None:
            try:
                import pyrealsense2 as rs
            except ImportError as exc:
                raise FrameError(
                    "camera source 'realsense' needs pyrealsense2: install the 'realsense' extra"
                ) from exc
            self._rs = rs
        rs = self._rs
        try:
            if self._pipeline is None:
                self._pipeline = rs.pipeline()
            config = rs.config()
            if self.serial:
                config.enable_device(self.serial)
            fps = int(round(self.rate_hz))
            config.enable_stream(rs.stream.depth, self.width_px, self.height_px, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, self.width_px, self.height_px, rs.format.rgb8, fps)
            profile = self._pipeline.start(config)
            self.depth_scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
            vsp = profile.get_stream(rs.stream.color).as_video_stream_profile()
            ri = vsp.get_intrinsics()
            self._intrinsics = CameraIntrinsics(
                float(ri.fx), float(ri.fy), float(ri.ppx), float(ri.ppy), int(ri.width), int(ri.height)
            )
            self._align = rs.align(rs.stream.color)
            self._enable_global_time(profile.get_device())
        except RuntimeError as exc:
            who = f"RealSense {self.serial}" if self.serial else "RealSense camera"
            raise FrameError(f"{who}: cannot start {self.width_px}x{self.height_px} "
                             f"@ {self.rate_hz:g} Hz: {exc}") from exc
        self._running = True
        log.info("RealSense started: %dx%d @ %g Hz, depth scale %.5f m, fx %.1f", self.width_px,
                 self.height_px, self.rate_hz, self.depth_scale_m, self._intrinsics.fx_px)

    def _enable_global_time(self, device: Any) -> None:
        """Switch librealsense's global time on where a sensor offers it (off on some SKUs)."""
        option = self._rs.option.global_time_enabled
        for sensor in device.query_sensors():
            try:
                if sensor.supports(option) and not sensor.get_option(option):
                    sensor.set_option(option, 1)
            except RuntimeError as exc:
                log.warning("RealSense: cannot switch global time on: %s", exc)

    def close(self) -> None:
        """Stop the pipeline. Idempotent."""
        if not self._running:
            return
        self._running = False
        try:
            self._pipeline.stop()
        except RuntimeError as exc:
            log.warning("RealSense stop failed: %s", exc)

    def read(self) -> Frame | None:
        """The next aligned frame; skips bad ones (counted) and raises :class:`FrameError`
        after ``max_consecutive_failures`` in a row."""
        self.open()
        while True:
            frame, reason = self._try_read()
            if frame is not None:
                self._consecutive_failures = 0
                self.frames_read += 1
                return frame
            self.dropped_frames += 1
            self._consecutive_failures += 1
            log.warning("RealSense frame dropped (%s); %d dropped so far", reason, self.dropped_frames)
            if self._consecutive_failures >= self.max_consecutive_failures:
                raise FrameError(
                    f"RealSense camera: {self._consecutive_failures} bad frames in a row "
                    f"(last: {reason})"
                )

    def _try_read(self) -> tuple[Frame | None, str]:
        intr = self._intrinsics
        assert intr is not None
        try:
            frames = self._pipeline.wait_for_frames(self.timeout_ms)
            aligned = self._align.process(frames)
            depth_f = aligned.get_depth_frame()
            color_f = aligned.get_color_frame()
        except RuntimeError as exc:
            return None, f"no frames: {exc}"
        if not depth_f or not color_f:
            return None, "incomplete frame set"
        depth_raw = np.asanyarray(depth_f.get_data())
        rgb = np.asanyarray(color_f.get_data())
        shape_hw = (intr.height_px, intr.width_px)
        if depth_raw.shape != shape_hw or depth_raw.dtype != np.uint16:
            return None, f"depth is {depth_raw.dtype} {depth_raw.shape}, expected uint16 {shape_hw}"
        if rgb.shape != (*shape_hw, 3) or rgb.dtype != np.uint8:
            return None, f"colour is {rgb.dtype} {rgb.shape}, expected uint8 {(*shape_hw, 3)}"
        depth = depth_raw.astype(np.float32) * np.float32(self.depth_scale_m)
        depth[(depth < self.depth_min_m) | (depth > self.depth_max_m)] = 0.0
        arrival_s, arrival_wall_s = time.monotonic(), time.time()
        try:
            # The depth frame's stamp: the geometry comes from it (colour is hardware-synced).
            self.last_device_stamp_ms = float(depth_f.get_timestamp())
            self.last_stamp_domain = _domain_name(depth_f.get_frame_timestamp_domain())
        except (AttributeError, RuntimeError):
            self.last_device_stamp_ms, self.last_stamp_domain = 0.0, "unknown"
        stamp_s = self.capture_clock.capture_stamp_s(
            self.last_device_stamp_ms, self.last_stamp_domain, arrival_s, arrival_wall_s)
        self.last_latency_s = arrival_s - stamp_s
        return Frame(
            stamp_s=stamp_s, rgb=np.array(rgb, dtype=np.uint8, copy=True), depth_m=depth,
            intrinsics=intr, T_map_camera=None, index=self.frames_read,
        ), ""
