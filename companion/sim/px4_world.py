"""The simulated room around a real autopilot (PX4 SITL, or any vehicle on a MAVLink link).

With the mock autopilot the simulator owns the vehicle (:class:`~companion.sim.sim_world.SimWorld`);
here the autopilot does: the world only renders the simulated RealSense from the pose the
autopilot reports. :class:`Px4World` places the seeded room so the vehicle's start point is
just inside its first doorway, follows the autopilot's telemetry on a MAVLink link (the
service's own) and publishes each pose to the camera, which may render in the perception
process (:class:`~companion.sim.sim_world.SharedSimState`).

Frames: the map frame is PX4's local frame in ENU (x east, y north); the world's z is the
height above the floor as the downward range finder measures it (SIH simulates one), else
the local z the vehicle had while it last stood landed and disarmed (:class:`FlightTimeline`):
PX4's local z is not the floor, and home's z moves in flight.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.config import CompanionConfig, LinkConfig
from companion.errors import LinkError
from companion.mavlink.link import MavlinkLink
from companion.mavlink.state import LandedState, LinkLike, MapFrame
from companion.px4 import decode_heartbeat
from companion.sim.sim_world import (
    SharedSimState,
    SimCameraSource,
    SimPlacement,
    start_point_room_m,
)
from companion.sim.world import Room
from companion.sources.sim import room_from_config
from semmap.frames import map_pose_from_ned

log = logging.getLogger(__name__)

#: The flown path keeps a sample at most this often (seconds).
PATH_PERIOD_S = 0.05
#: A position older than this (autopilot time) is not moved on to an attitude's time.
MAX_POSITION_AGE_S = 0.2


@dataclass(frozen=True)
class FlightEvent:
    """A change of mode, arming or landed state, where the vehicle was (map frame, z above
    the floor; None before the first position) and its height above home as PX4 reports it."""

    t_s: float
    mode: str
    armed: bool
    landed: str
    xyz_map_m: tuple[float, float, float] | None
    height_above_home_m: float | None = None
    range_m: float | None = None
    #: For a change a heartbeat reported: when the heartbeat before it came (the change
    #: happened after that); None otherwise.
    after_t_s: float | None = None


class FlightTimeline:
    """Records the autopilot's mode, arming, landed state and position from a link
    (``attach``), as the vehicle reports them. Positions: x east, y north of PX4's local
    origin, z the height above the floor: the downward range finder's distance
    (DISTANCE_SENSOR, orientation down) carried on by the local z between its samples, else
    the local z the vehicle had while it last stood landed and disarmed, else home's z. Home's
    z is no floor in flight: PX4 (GPS height) recomputes it from the GNSS altitude, and it
    moves by up to a metre."""

    MESSAGES = ("HEARTBEAT", "EXTENDED_SYS_STATE", "LOCAL_POSITION_NED", "HOME_POSITION", "DISTANCE_SENSOR")

    def __init__(self, target_system: int = 1, target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
                 path_period_s: float = 0.05) -> None:
        self.target_system = target_system
        self.target_component = target_component
        self.path_period_s = path_period_s
        self.events: list[FlightEvent] = []
        #: (t_s, x, y, z) map frame, at most every ``path_period_s``.
        self.path: list[tuple[float, float, float, float]] = []
        self.mode = "UNKNOWN"
        self.armed = False
        self.landed = LandedState.UNDEFINED.name
        self.home_down_m: float | None = None
        self.floor_down_m: float | None = None
        #: The latest downward range (metres), None before the first.
        self.range_m: float | None = None
        self.xyz_map_m: tuple[float, float, float] | None = None
        self.ned_m: tuple[float, float, float] | None = None
        self._heartbeat_t_s: float | None = None

    def attach(self, link: LinkLike) -> Callable[[], None]:
        return link.add_listener(self.handle, self.MESSAGES)

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != self.target_component:
            return
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                return
            d = decode_heartbeat(msg.base_mode, msg.custom_mode)
            previous, self._heartbeat_t_s = self._heartbeat_t_s, time.monotonic()
            self._update(d.mode.name if d.mode else f"main{d.main_mode}/sub{d.sub_mode}", d.armed, self.landed,
                         after_t_s=previous)
        elif mtype == "EXTENDED_SYS_STATE":
            self._update(self.mode, self.armed, LandedState.from_mavlink(msg.landed_state).name)
        elif mtype == "HOME_POSITION" and math.isfinite(msg.z):
            self.home_down_m = float(msg.z)
        elif mtype == "DISTANCE_SENSOR":
            cm = int(msg.current_distance)
            if msg.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270 and self.ned_m is not None \
                    and msg.min_distance <= cm <= msg.max_distance:
                self.range_m = cm / 100.0
                self.floor_down_m = self.ned_m[2] + self.range_m
        elif mtype == "LOCAL_POSITION_NED":
            self.ned_m = (float(msg.x), float(msg.y), float(msg.z))
            if self.range_m is None and not self.armed and self.landed == LandedState.ON_GROUND.name:
                self.floor_down_m = self.ned_m[2]
            floor = self.floor_down_m if self.floor_down_m is not None else self.home_down_m
            if floor is None:
                return
            self.xyz_map_m = MapFrame(floor).from_ned(*self.ned_m)
            now = time.monotonic()
            if not self.path or now - self.path[-1][0] >= self.path_period_s:
                self.path.append((now, *self.xyz_map_m))

    def _update(self, mode: str, armed: bool, landed: str, after_t_s: float | None = None) -> None:
        if (mode, armed, landed) != (self.mode, self.armed, self.landed):
            self.mode, self.armed, self.landed = mode, armed, landed
            above_home = None if self.ned_m is None or self.home_down_m is None else self.home_down_m - self.ned_m[2]
            self.events.append(FlightEvent(time.monotonic(), mode, armed, landed, self.xyz_map_m, above_home,
                                           self.range_m, after_t_s))
            log.info("timeline: %s, %s, %s at %s", mode, "armed" if armed else "disarmed", landed,
                     "?" if self.xyz_map_m is None else "({:.2f}, {:.2f}, {:.2f}) m".format(*self.xyz_map_m))

    @property
    def in_air(self) -> bool:
        return self.landed in ("IN_AIR", "TAKEOFF", "LANDING")

    async def wait_for(self, predicate: Callable[[FlightTimeline], bool], timeout_s: float, what: str) -> None:
        """Poll until ``predicate(self)``; raises :class:`LinkError` naming ``what`` on timeout."""
        deadline = time.monotonic() + timeout_s
        while not predicate(self):
            if time.monotonic() > deadline:
                raise LinkError(f"timed out after {timeout_s:.0f} s waiting for {what} "
                                f"(now {self.mode}, {'armed' if self.armed else 'disarmed'}, {self.landed})")
            await asyncio.sleep(0.05)

    def max_distance_from_m(self, xy: tuple[float, float]) -> float:
        return max((math.hypot(p[1] - xy[0], p[2] - xy[1]) for p in self.path), default=0.0)


class Px4World:
    """The seeded room of ``cfg`` around a vehicle that stands at ``start_map_xy_m`` (map
    frame) on the floor: the room is placed so that point is just inside the first doorway.

    :meth:`follow` attaches it to a MAVLink link; from then on every ATTITUDE of the autopilot
    (``target_system``/``target_component``) with its latest LOCAL_POSITION_NED, moved on by
    its velocity to the attitude's time, is one camera pose and, every ``PATH_PERIOD_S``, a
    point of :attr:`path_map_m`. Nothing is published before the floor is known."""

    def __init__(self, cfg: CompanionConfig, start_map_xy_m: tuple[float, float], *, target_system: int = 1,
                 target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1) -> None:
        room = room_from_config(cfg)
        sx, sy = start_point_room_m(room)
        self.cfg = cfg
        self.placement = SimPlacement(room, (sx - start_map_xy_m[0], sy - start_map_xy_m[1]))
        self.shared = SharedSimState()
        self.target_system = target_system
        self.target_component = target_component
        #: Mode, arming, landed state and the floor's local z, from the same telemetry.
        self.timeline = FlightTimeline(target_system, target_component)
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
        detach = self.timeline.attach(link)
        remove = link.add_listener(self.handle, ("LOCAL_POSITION_NED", "ATTITUDE"))

        def stop() -> None:
            detach()
            remove()

        return stop

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        """One telemetry message (others' and other types are ignored)."""
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != self.target_component:
            return
        mtype = msg.get_type()
        if mtype == "LOCAL_POSITION_NED":
            vals = (msg.time_boot_ms * 1e-3, msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if all(math.isfinite(v) for v in vals):
                self._pos = tuple(float(v) for v in vals)
            return
        floor = self.timeline.floor_down_m if self.timeline.floor_down_m is not None else self.timeline.home_down_m
        if mtype != "ATTITUDE" or self._pos is None or floor is None:
            return
        boot_s, n, e, d, vn, ve, vd = self._pos
        dt = msg.time_boot_ms * 1e-3 - boot_s
        rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
        if abs(dt) > MAX_POSITION_AGE_S or not all(math.isfinite(v) for v in rpy):
            return
        ned = (n + vn * dt, e + ve * dt, d + vd * dt)
        T_map_body = map_pose_from_ned(ned, rpy)
        # The room's floor is where the vehicle stood: PX4's local origin is not the floor.
        T_map_body[:3, 3] = MapFrame(floor).from_ned(*ned)
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
