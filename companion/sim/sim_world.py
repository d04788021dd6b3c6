"""The simulated world the service flies in when ``camera.source`` is ``sim``.

A seeded furnished room (``cfg.sim``), the mock PX4 autopilot and the simulated RealSense
riding on the mock vehicle. The mock's map frame is its local NED origin (home), where the
vehicle boots; the room is generated in its own frame (interior ``[0, w] x [0, d]``), so it is
placed with a free start point just inside the first doorway at the map origin:
``T_room_map`` is that translation. Frames are rendered in the room and handed to the
service with ``T_map_camera`` in the map frame, exactly as a real camera with the
autopilot's pose would give them.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing as mp
import time
from dataclasses import dataclass, replace
from types import TracebackType
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.background import end_task
from companion.config import CompanionConfig
from companion.errors import SimulationError
from companion.geo import GeoOrigin
from companion.mavlink.signing import read_key_file
from companion.shared_record import SharedRecord
from companion.sim.autopilot import MockAutopilot
from companion.sim.odometry import OdometryDriftModel
from companion.sim.render import renderer_from_config
from companion.sim.world import Room
from companion.sources.base import FrameSource
from companion.sources.sim import SimFrameSource, room_from_config
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: How far inside the first doorway the vehicle boots (metres).
START_INSIDE_M = 0.9
#: How often the vehicle pose is handed to the simulated camera (the mock's physics runs at 100 Hz).
POSE_PERIOD_S = 0.01


def start_point_room_m(room: Room) -> tuple[float, float]:
    """Where the vehicle boots, in the room frame: just inside the first doorway."""
    if not room.doorways:
        raise SimulationError("the simulated room has no doorway to start from")
    return room.doorways[0].inside_point_m(START_INSIDE_M)


def drift_from_config(cfg: CompanionConfig) -> OdometryDriftModel | None:
    """The mock autopilot's odometry drift of ``cfg.sim`` (None when ``odometry_drift`` is off)."""
    s = cfg.sim
    if not s.odometry_drift:
        return None
    return OdometryDriftModel(s.odometry_scale_error, s.odometry_heading_drift_deg_s,
                              s.odometry_noise_m_per_sqrt_m, s.odometry_noise_rad_per_sqrt_rad, seed=s.seed)


@dataclass(frozen=True)
class SimPlacement:
    """The room and where it sits in the map frame (``xy_room = xy_map + offset``)."""

    room: Room
    offset_xy_m: tuple[float, float]

    def map_to_room(self, xyz_map_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 3) map-frame points -> room-frame points (for the ground-truth judges)."""
        p = np.asarray(xyz_map_m, dtype=np.float64).reshape(-1, 3).copy()
        p[:, 0] += self.offset_xy_m[0]
        p[:, 1] += self.offset_xy_m[1]
        return p

    def room_to_map_xy(self, xy_room_m: tuple[float, float]) -> tuple[float, float]:
        """A room-frame point in the map frame."""
        return xy_room_m[0] - self.offset_xy_m[0], xy_room_m[1] - self.offset_xy_m[1]

    @property
    def T_map_room(self) -> NDArray[np.float64]:  # noqa: N802 - frame names
        T = np.eye(4)
        T[0, 3], T[1, 3] = -self.offset_xy_m[0], -self.offset_xy_m[1]
        return T


class SimPoses(NamedTuple):
    """One published instant of the simulated vehicle: ``monotonic_s`` (its time on
    ``time.monotonic``, the clock a camera stamps frames with), the true ``T_map_body`` and
    the autopilot's estimate (None when it is the truth)."""

    monotonic_s: float
    T_map_body: NDArray[np.float64]
    T_map_body_estimated: NDArray[np.float64] | None
    #: The body pose in the autopilot's odometry frame (never vision-corrected), None with the estimate.
    T_odom_body: NDArray[np.float64] | None = None


class SharedSimState:
    """The simulated vehicle's pose and the camera fault switches in shared memory, so the
    simulated camera can render in another process (the perception process) while the mock
    autopilot flies in this one. Written by :class:`SimWorld`, read by :class:`SimCameraSource`;
    picklable into a ``spawn`` child while it starts."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        # [valid, monotonic_s, T_map_body (16, row-major), estimated (0/1), the autopilot's
        # estimated T_map_body (16), odometry (0/1), T_odom_body (16)]; written by the world,
        # read by the camera, neither waiting on the other.
        self._pose = SharedRecord(52)
        self._missing = ctx.Value("b", 0, lock=False)
        self._corrupt = ctx.Value("b", 0, lock=False)

    def set_pose(self, monotonic_s: float, T_map_body: NDArray[np.floating],  # noqa: N803 - frame names
                 T_map_body_estimated: NDArray[np.floating] | None = None,  # noqa: N803
                 T_odom_body: NDArray[np.floating] | None = None) -> None:  # noqa: N803
        """Publish the vehicle pose (``T_map_body`` (4, 4), map frame) at ``monotonic_s``
        (``time.monotonic``), and the autopilot's estimate of it when that differs (odometry
        drift) with its odometry pose (``T_odom_body``, never vision-corrected)."""
        def flag(T: NDArray[np.floating] | None) -> list[float]:
            return [1.0, *np.asarray(T, dtype=np.float64).reshape(16).tolist()] if T is not None else [0.0] * 17

        vals = [1.0, float(monotonic_s), *np.asarray(T_map_body, dtype=np.float64).reshape(16).tolist(),
                *flag(T_map_body_estimated), *flag(T_odom_body)]
        self._pose.write(vals)

    def poses(self) -> SimPoses | None:
        """The instant, the pose and the estimate published together, or None before the first."""
        vals = self._pose.read()
        if vals is None or vals[0] == 0.0:
            return None
        est = np.asarray(vals[19:35], dtype=np.float64).reshape(4, 4) if vals[18] else None
        odo = np.asarray(vals[36:52], dtype=np.float64).reshape(4, 4) if vals[35] else None
        return SimPoses(vals[1], np.asarray(vals[2:18], dtype=np.float64).reshape(4, 4), est, odo)

    @property
    def camera_missing(self) -> bool:
        return bool(self._missing.value)

    @camera_missing.setter
    def camera_missing(self, on: bool) -> None:
        self._missing.value = int(on)

    @property
    def camera_corrupt(self) -> bool:
        return bool(self._corrupt.value)

    @camera_corrupt.setter
    def camera_corrupt(self, on: bool) -> None:
        self._corrupt.value = int(on)


class SimCameraSource(FrameSource):
    """The simulated RealSense on the mock vehicle: renders ``room`` from the pose in
    ``shared`` and returns frames posed in the map frame (``T_map_room`` applied), exactly as
    a real camera with the autopilot's pose gives them. Picklable: the renderer is built on
    first use, in whichever process reads the camera."""

    def __init__(self, cfg: CompanionConfig, placement: SimPlacement, shared: SharedSimState) -> None:
        self.cfg = cfg
        self.placement = placement
        self.shared = shared
        self.dropped_frames = 0
        self._inner: SimFrameSource | None = None
        #: The autopilot's estimate of the pose the latest frame was rendered from, and its
        #: odometry pose.
        self._estimated: NDArray[np.float64] | None = None
        self._odometry: NDArray[np.float64] | None = None

    def _source(self) -> SimFrameSource:
        if self._inner is None:
            T_room_map = np.linalg.inv(self.placement.T_map_room)

            def pose_room() -> tuple[float, NDArray[np.float64]] | None:
                p = self.shared.poses()
                while p is None:  # the world has not published a pose yet
                    time.sleep(0.02)
                    p = self.shared.poses()
                self._estimated, self._odometry = p.T_map_body_estimated, p.T_odom_body
                # Stamped on this machine's clock at capture, as a RealSense stamps its frames.
                return p.monotonic_s, T_room_map @ p.T_map_body

            self._inner = SimFrameSource(renderer_from_config(self.placement.room, self.cfg), pose_room,
                                         self.cfg.camera.extrinsics.T_body_camera())
        return self._inner

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_inner": None}

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.cfg.camera.intrinsics()

    def open(self) -> None:
        self._source().open()

    def close(self) -> None:
        if self._inner is not None:
            self._inner.close()

    def read(self) -> Frame | None:
        while self.shared.camera_missing:
            # A camera that delivers nothing: read() blocks, as a stalled USB camera does.
            time.sleep(0.02)
        src = self._source()
        frame = src.read()
        self.frames_read = src.frames_read
        if frame is None or frame.T_map_camera is None:
            return frame
        if self.cfg.sim.camera_pose == "telemetry":
            # As a RealSense delivers it: no pose (the service looks it up in the telemetry).
            frame = replace(frame, T_map_camera=None)
        elif self._estimated is not None:
            # Rendered where the vehicle is, posed where the autopilot thinks it is.
            frame = replace(frame, T_map_camera=self._estimated @ src.T_body_camera, T_odom_body=self._odometry)
        else:
            frame = replace(frame, T_map_camera=self.placement.T_map_room @ np.asarray(frame.T_map_camera))
        if self.shared.camera_corrupt:
            # Garbage images: random colour, depth invalid or absurd.
            rng = np.random.default_rng(frame.index)
            depth = rng.uniform(-5.0, 50.0, frame.depth_m.shape).astype(np.float32)
            depth[rng.random(depth.shape) < 0.5] = np.nan
            frame = replace(frame, rgb=rng.integers(0, 255, frame.rgb.shape, dtype=np.uint8), depth_m=depth,
                            masks={})
        return frame


class SimWorld:
    """Mock autopilot + simulated camera for ``cfg`` (async context manager).

    ``autopilot_port``: the mock's UDP port (0 = any free port); ``remote_ports``: where it
    sends (the service's link, MAVSDK, a ground station). Read ``autopilot.local_port``
    after entering. While entered, the vehicle's pose is published to the camera every
    ``POSE_PERIOD_S`` (shared memory, so the camera may render in the perception process).
    """

    def __init__(self, cfg: CompanionConfig, *, autopilot_port: int | None = None,
                 remote_ports: tuple[int, ...] | None = None, params: dict[str, float] | None = None) -> None:
        s = cfg.sim
        room = room_from_config(cfg)
        self.placement = SimPlacement(room, start_point_room_m(room))
        self.autopilot = MockAutopilot(
            local_port=s.autopilot_local_port if autopilot_port is None else autopilot_port,
            remote_ports=(s.autopilot_offboard_port, s.autopilot_gcs_port) if remote_ports is None else remote_ports,
            home=GeoOrigin(s.home_lat_deg, s.home_lon_deg, s.home_alt_m),
            params={"COM_DISARM_PRFLT": -1.0, **(params or {})}, seed=s.seed,
            odometry_drift=drift_from_config(cfg), vision_gain=s.vision_fusion_gain, gps_denied=s.gps_denied,
        )
        if cfg.link.signing_key_path is not None:
            # The mock autopilot signs like PX4 with MAV_SIGN_CFG: the companion's link (the
            # first remote) must sign; the ground station ports stand for PX4's exempt USB link.
            ports = (s.autopilot_offboard_port, s.autopilot_gcs_port) if remote_ports is None else remote_ports
            self.autopilot.enable_signing(read_key_file(cfg.link.signing_key_path),
                                          tuple(("127.0.0.1", p) for p in ports[1:]))
        self.cfg = cfg
        self.shared = SharedSimState()
        self._pose_task: asyncio.Task[None] | None = None

    @property
    def room(self) -> Room:
        return self.placement.room

    # Fault injection: the camera delivers nothing / garbage while these are True.
    @property
    def camera_missing(self) -> bool:
        return self.shared.camera_missing

    @camera_missing.setter
    def camera_missing(self, on: bool) -> None:
        self.shared.camera_missing = on

    @property
    def camera_corrupt(self) -> bool:
        return self.shared.camera_corrupt

    @camera_corrupt.setter
    def camera_corrupt(self, on: bool) -> None:
        self.shared.camera_corrupt = on

    async def __aenter__(self) -> SimWorld:
        await self.autopilot.__aenter__()
        self._publish_pose()
        self._pose_task = asyncio.create_task(self._pose_loop(), name="sim-camera-pose")
        log.info("simulated world: room seed %d (%.1f x %.1f m, %d objects), mock autopilot on UDP %d",
                 self.room.seed, self.room.width_m, self.room.depth_m, len(self.room.objects),
                 self.autopilot.local_port)
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        task, self._pose_task = self._pose_task, None
        try:
            await end_task(task, "the simulated camera's pose loop")
        finally:
            await self.autopilot.__aexit__(exc_type, exc, tb)

    def _publish_pose(self) -> None:
        _, T_map_body, T_est = self.autopilot.poses_map_body()
        active = self.autopilot.estimator.active
        self.shared.set_pose(self.autopilot.tick_monotonic_s, np.asarray(T_map_body),
                             np.asarray(T_est) if active else None,
                             np.asarray(self.autopilot.T_odom_body()) if active else None)

    async def _pose_loop(self) -> None:
        while True:
            self._publish_pose()
            await asyncio.sleep(POSE_PERIOD_S)

    def frame_source(self) -> SimCameraSource:
        """The simulated camera on the mock vehicle, frames posed in the map frame
        (picklable: it may render in the perception process)."""
        return SimCameraSource(self.cfg, self.placement, self.shared)
