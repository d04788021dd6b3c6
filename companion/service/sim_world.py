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

import logging
import time
from dataclasses import dataclass, replace
from types import TracebackType

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from companion.geo import GeoOrigin
from companion.sim.autopilot import MockAutopilot
from companion.sim.render import renderer_from_config
from companion.sim.world import Room
from companion.sources.base import FrameSource
from companion.sources.sim import SimFrameSource, room_from_config
from semmap.errors import SimulationError
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: How far inside the first doorway the vehicle boots (metres).
START_INSIDE_M = 0.9


def start_point_room_m(room: Room) -> tuple[float, float]:
    """Where the vehicle boots, in the room frame: just inside the first doorway."""
    if not room.doorways:
        raise SimulationError("the simulated room has no doorway to start from")
    return room.doorways[0].inside_point_m(START_INSIDE_M)


class _MapFrameSource(FrameSource):
    """Renders in the room frame, returns frames whose pose is in the map frame."""

    def __init__(self, inner: SimFrameSource, T_map_room: NDArray[np.float64], world: SimWorld) -> None:
        self.inner = inner
        self.T_map_room = T_map_room
        self.world = world
        self.dropped_frames = 0

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.inner.intrinsics

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def read(self) -> Frame | None:
        while self.world.camera_missing:
            # A camera that delivers nothing: read() blocks, as a stalled USB camera does.
            time.sleep(0.02)
        frame = self.inner.read()
        if frame is None or frame.T_map_camera is None:
            return frame
        frame = replace(frame, T_map_camera=self.T_map_room @ np.asarray(frame.T_map_camera))
        if self.world.camera_corrupt:
            # Garbage images: random colour, depth invalid or absurd.
            rng = np.random.default_rng(frame.index)
            depth = rng.uniform(-5.0, 50.0, frame.depth_m.shape).astype(np.float32)
            depth[rng.random(depth.shape) < 0.5] = np.nan
            frame = replace(frame, rgb=rng.integers(0, 255, frame.rgb.shape, dtype=np.uint8), depth_m=depth,
                            masks={})
        return frame


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


class SimWorld:
    """Mock autopilot + simulated camera for ``cfg`` (async context manager).

    ``autopilot_port``: the mock's UDP port (0 = any free port); ``remote_ports``: where it
    sends (the service's link, MAVSDK, a ground station). Read ``autopilot.local_port``
    after entering.
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
        )
        self.cfg = cfg
        #: Fault injection: the camera delivers nothing / garbage while these are True.
        self.camera_missing = False
        self.camera_corrupt = False

    @property
    def room(self) -> Room:
        return self.placement.room

    async def __aenter__(self) -> SimWorld:
        await self.autopilot.__aenter__()
        log.info("simulated world: room seed %d (%.1f x %.1f m, %d objects), mock autopilot on UDP %d",
                 self.room.seed, self.room.width_m, self.room.depth_m, len(self.room.objects),
                 self.autopilot.local_port)
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self.autopilot.__aexit__(exc_type, exc, tb)

    def _pose_room(self) -> tuple[float, NDArray[np.float64]] | None:
        stamp, T_map_body = self.autopilot.T_map_body()
        T_room_body = np.linalg.inv(self.placement.T_map_room) @ np.asarray(T_map_body)
        return float(stamp), T_room_body

    def frame_source(self) -> FrameSource:
        """The simulated camera on the mock vehicle, frames posed in the map frame."""
        inner = SimFrameSource(renderer_from_config(self.room, self.cfg), self._pose_room,
                               self.cfg.camera.extrinsics.T_body_camera())
        return _MapFrameSource(inner, self.placement.T_map_room, self)
