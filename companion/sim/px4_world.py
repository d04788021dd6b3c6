"""The simulated room around a real autopilot (PX4 SITL, or any vehicle on a MAVLink link).

With the mock autopilot the simulator owns the vehicle (:class:`~companion.service.sim_world.SimWorld`);
here the autopilot does: the world only renders the simulated RealSense from the pose the
autopilot reports. :class:`Px4World` places the seeded room so the vehicle's start point is
just inside its first doorway, follows the autopilot's telemetry on a MAVLink link (the
service's own) and publishes each pose to the camera, which may render in the perception
process (:class:`~companion.service.sim_world.SharedSimState`).

Frames: the map frame is PX4's local frame in ENU with the height above home as z (PX4's
local z is not the floor); the room floor is at z = 0 of the map frame, since the vehicle
boots on the floor at home.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig, LinkConfig
from companion.errors import LinkError
from companion.mavlink.link import MavlinkLink
from companion.mavlink.state import LinkLike, MapFrame
from companion.service.sim_world import (
    SharedSimState,
    SimCameraSource,
    SimPlacement,
    start_point_room_m,
)
from companion.sim.world import Room
from companion.sources.poses import map_pose_from_ned
from companion.sources.sim import room_from_config

log = logging.getLogger(__name__)

#: The flown path keeps a sample at most this often (seconds).
PATH_PERIOD_S = 0.05
#: A position older than this (autopilot time) is not moved on to an attitude's time.
MAX_POSITION_AGE_S = 0.2


class Px4World:
    """The seeded room of ``cfg`` around a vehicle that stands at ``start_map_xy_m`` (map
    frame) on the floor: the room is placed so that point is just inside the first doorway.

    :meth:`follow` attaches it to a MAVLink link; from then on every ATTITUDE of the autopilot
    (``target_system``/``target_component``) with its latest LOCAL_POSITION_NED, moved on by
    its velocity to the attitude's time, is one camera pose and, every ``PATH_PERIOD_S``, a
    point of :attr:`path_map_m`. Nothing is published before HOME_POSITION (the height
    reference) has arrived."""

    def __init__(self, cfg: CompanionConfig, start_map_xy_m: tuple[float, float], *, target_system: int = 1,
                 target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1) -> None:
        room = room_from_config(cfg)
        sx, sy = start_point_room_m(room)
        self.cfg = cfg
        self.placement = SimPlacement(room, (sx - start_map_xy_m[0], sy - start_map_xy_m[1]))
        self.shared = SharedSimState()
        self.target_system = target_system
        self.target_component = target_component
        self._home_down_m: float | None = None
        self._pos: tuple[float, ...] | None = None  # boot_s, n, e, d, vn, ve, vd
        self._lock = threading.Lock()
        self._path: list[tuple[float, float, float, float]] = []  # monotonic_s, x, y, z
        self.poses_published = 0

    @property
    def room(self) -> Room:
        return self.placement.room

    def frame_source(self) -> SimCameraSource:
        """The simulated camera on the vehicle, rendering the room from the published poses
        (picklable: it may render in the perception process)."""
        return SimCameraSource(self.cfg, self.placement, self.shared)

    def follow(self, link: LinkLike) -> Callable[[], None]:
        """Follow the autopilot's telemetry on ``link``; returns the function that stops it."""
        return link.add_listener(self.handle, ("HOME_POSITION", "LOCAL_POSITION_NED", "ATTITUDE"))

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        """One telemetry message (others' and other types are ignored)."""
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != self.target_component:
            return
        mtype = msg.get_type()
        if mtype == "HOME_POSITION":
            if math.isfinite(msg.z):
                if self._home_down_m is None:
                    log.info("simulated world: home at local z %.2f m (NED); the room floor is there", msg.z)
                self._home_down_m = float(msg.z)
        elif mtype == "LOCAL_POSITION_NED":
            vals = (msg.time_boot_ms * 1e-3, msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if all(math.isfinite(v) for v in vals):
                self._pos = tuple(float(v) for v in vals)
        elif mtype == "ATTITUDE" and self._pos is not None and self._home_down_m is not None:
            boot_s, n, e, d, vn, ve, vd = self._pos
            dt = msg.time_boot_ms * 1e-3 - boot_s
            rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
            if abs(dt) > MAX_POSITION_AGE_S or not all(math.isfinite(v) for v in rpy):
                return
            ned = (n + vn * dt, e + ve * dt, d + vd * dt)
            T_map_body = map_pose_from_ned(ned, rpy)
            # Height above home: PX4's local origin is where the EKF started, not the floor.
            T_map_body[:3, 3] = MapFrame(self._home_down_m).from_ned(*ned)
            now = time.monotonic()
            self.shared.set_pose(now, T_map_body)
            self.poses_published += 1
            with self._lock:
                if not self._path or now - self._path[-1][0] >= PATH_PERIOD_S:
                    self._path.append((now, *(float(v) for v in T_map_body[:3, 3])))

    @property
    def path_map_m(self) -> NDArray[np.float64]:
        """(N, 3) the flown path in the map frame (z above home), oldest first."""
        with self._lock:
            rows = [p[1:] for p in self._path]
        return np.asarray(rows, dtype=np.float64).reshape(-1, 3)

    def position_map_m(self) -> NDArray[np.float64] | None:
        """The latest published position (3,), map frame, or None before the first."""
        poses = self.shared.poses()
        return None if poses is None else np.asarray(poses.T_map_body[:3, 3], dtype=np.float64)



async def vehicle_start_map_xy(link_cfg: LinkConfig, timeout_s: float = 30.0) -> tuple[float, float]:
    """Where the vehicle on ``link_cfg.url`` stands now, map frame (x east, y north of PX4's
    local origin), from its first LOCAL_POSITION_NED; the link is closed again on return."""
    got: asyncio.Future[tuple[float, float]] = asyncio.get_running_loop().create_future()

    def on_position(msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != link_cfg.target_system or msg.get_srcComponent() != link_cfg.target_component:
            return
        if not got.done() and math.isfinite(msg.x) and math.isfinite(msg.y):
            got.set_result((float(msg.y), float(msg.x)))

    async with MavlinkLink.from_config(link_cfg) as link:
        link.add_listener(on_position, ("LOCAL_POSITION_NED",))
        try:
            return await asyncio.wait_for(got, timeout_s)
        except TimeoutError:
            raise LinkError(f"no local position from the autopilot (system {link_cfg.target_system}) on "
                            f"{link_cfg.url} within {timeout_s:.0f} s") from None
