"""OBSTACLE_DISTANCE from the costmap, so PX4's collision prevention is a second line of defence.

The encoder casts rays from the vehicle through the costmap (map frame, ENU) and reports, per
sector of the vehicle's horizontal plane, the distance to the nearest ``LETHAL_OBSTACLE``
cell, following the MAVLink ``OBSTACLE_DISTANCE`` message:

* ``frame = MAV_FRAME_BODY_FRD``: sector angles are relative to the vehicle's nose,
  clockwise positive; element ``i`` is centred on ``angle_offset + i * increment_f`` degrees.
  We use 72 sectors of 5 deg with ``angle_offset = 0`` (sector 0 centred straight ahead).
* distances in centimetres; an obstacle closer than ``min_distance`` is reported at
  ``min_distance`` (the closest the "sensor" can claim);
* ``max_distance + 1``: no obstacle within range (at least one ray of the sector crossed
  known cells all the way to ``max_distance``);
* ``UINT16_MAX``: unknown - every ray of the sector ran into unmapped cells
  (``NO_INFORMATION`` or off the grid) before reaching range without meeting an obstacle.
  With ``unknown_is_obstacle`` unmapped cells count as obstacles instead.

:class:`ObstacleDistanceFeed` sends it at a fixed rate (10 Hz by default); the ray casting
runs in a worker thread so it never delays the setpoint task on the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.background import BackgroundPart
from companion.mavlink.link import MavlinkLink
from companion.mavlink.state import VehicleState
from semmap.costmap import LETHAL_OBSTACLE, NO_INFORMATION, Costmap
from semmap.frames import ned_to_enu, yaw_ned_to_enu

log = logging.getLogger(__name__)

UINT16_MAX = 0xFFFF
N_SECTORS = 72  # the message's fixed array length


@dataclass(frozen=True)
class ObstacleDistanceScan:
    """One OBSTACLE_DISTANCE worth of data (body FRD sectors, centimetres)."""

    distances_cm: tuple[int, ...]  # (72,)
    min_distance_cm: int
    max_distance_cm: int
    increment_deg: float
    angle_offset_deg: float
    frame: int = mavlink.MAV_FRAME_BODY_FRD

    def sector_center_deg(self, i: int) -> float:
        """Centre of sector ``i``: degrees from the nose, clockwise."""
        return self.angle_offset_deg + i * self.increment_deg

    def to_message(self, link: MavlinkLink, time_usec: int) -> mavlink.MAVLink_obstacle_distance_message:
        """The MAVLink message (``time_usec``: microseconds since our boot)."""
        return link.mav.obstacle_distance_encode(
            time_usec,
            mavlink.MAV_DISTANCE_SENSOR_UNKNOWN,
            list(self.distances_cm),
            int(round(self.increment_deg)),
            self.min_distance_cm,
            self.max_distance_cm,
            float(self.increment_deg),
            float(self.angle_offset_deg),
            self.frame,
        )


def compute_obstacle_distances(
    costmap: Costmap,
    xy_map_m: tuple[float, float],
    yaw_map_rad: float,
    *,
    min_distance_m: float = 0.2,
    max_distance_m: float = 8.0,
    rays_per_sector: int = 5,
    angle_offset_deg: float = 0.0,
    unknown_is_obstacle: bool = False,
) -> ObstacleDistanceScan:
    """Per-sector distance to the nearest lethal cell around a vehicle pose.

    ``xy_map_m``: vehicle position in the map frame (ENU, metres). ``yaw_map_rad``: its
    heading in the map frame (ENU: from +x east, counter-clockwise). Rays are sampled every
    half cell out to ``max_distance_m``; ``rays_per_sector`` rays spread evenly over each
    5-degree sector.
    """
    if not 0.0 <= min_distance_m < max_distance_m:
        raise ValueError(f"need 0 <= min_distance_m < max_distance_m (got {min_distance_m}, {max_distance_m})")
    if max_distance_m * 100.0 + 1 >= UINT16_MAX:
        raise ValueError(f"max_distance_m too large for uint16 centimetres (got {max_distance_m})")
    if rays_per_sector < 1:
        raise ValueError(f"rays_per_sector must be >= 1 (got {rays_per_sector})")
    increment_deg = 360.0 / N_SECTORS
    step_m = costmap.spec.resolution_m / 2.0
    ranges_m = np.arange(step_m, max_distance_m + 1e-9, step_m)  # (K,)
    # Body-FRD bearing (clockwise from the nose) of every ray: (S, R).
    offsets = ((np.arange(rays_per_sector) + 0.5) / rays_per_sector - 0.5) * increment_deg
    bearings_deg = angle_offset_deg + np.arange(N_SECTORS)[:, None] * increment_deg + offsets[None, :]
    # Clockwise in the body frame is clockwise in the (z-up) map frame too.
    theta = yaw_map_rad - np.radians(bearings_deg).reshape(-1)  # (S*R,)
    cost = _ray_costs(costmap, xy_map_m, theta, ranges_m)  # (S*R, K)

    lethal = cost == LETHAL_OBSTACLE
    unknown = cost == NO_INFORMATION
    if unknown_is_obstacle:
        lethal = lethal | unknown
    d_hit = _first_true_range(lethal, ranges_m)  # (S*R,) inf where none
    d_unknown = _first_true_range(unknown, ranges_m)
    ray_free = np.isinf(d_hit) & np.isinf(d_unknown)

    d_hit_s = d_hit.reshape(N_SECTORS, rays_per_sector).min(axis=1)
    free_s = ray_free.reshape(N_SECTORS, rays_per_sector).any(axis=1)
    min_cm = int(round(min_distance_m * 100.0))
    max_cm = int(round(max_distance_m * 100.0))
    out = np.full(N_SECTORS, UINT16_MAX, dtype=np.int64)
    out[free_s] = max_cm + 1
    hit = np.isfinite(d_hit_s)
    out[hit] = np.clip(np.round(d_hit_s[hit] * 100.0), min_cm, max_cm)
    return ObstacleDistanceScan(
        distances_cm=tuple(int(v) for v in out),
        min_distance_cm=min_cm,
        max_distance_cm=max_cm,
        increment_deg=increment_deg,
        angle_offset_deg=angle_offset_deg,
    )


def _ray_costs(
    costmap: Costmap, xy_map_m: tuple[float, float], theta_rad: NDArray[np.float64],
    ranges_m: NDArray[np.float64],
) -> NDArray[np.uint8]:
    """(M, K) cost under each sample of M rays (map-frame angles) at K ranges; off-grid
    samples read NO_INFORMATION. Works in cell units with one flat gather (the hot path)."""
    spec = costmap.spec
    rows_n, cols_n = spec.shape_rc
    res = spec.resolution_m
    x0 = (xy_map_m[0] - spec.origin_xy_m[0]) / res
    y0 = (xy_map_m[1] - spec.origin_xy_m[1]) / res
    steps = (ranges_m / res).astype(np.float32)[None, :]  # (1, K) in cells
    cols = np.floor(x0 + np.cos(theta_rad).astype(np.float32)[:, None] * steps).astype(np.int32)
    rows = np.floor(y0 + np.sin(theta_rad).astype(np.float32)[:, None] * steps).astype(np.int32)
    inside = (cols >= 0) & (cols < cols_n) & (rows >= 0) & (rows < rows_n)
    flat = np.where(inside, rows * cols_n + cols, 0)
    cost = costmap.cost.reshape(-1)[flat]
    cost[~inside] = NO_INFORMATION
    return cost


def _first_true_range(mask: NDArray[np.bool_], ranges_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, K) mask -> (N,) range of the first True per row, inf where the row has none."""
    first = np.argmax(mask, axis=1)
    any_true = mask[np.arange(mask.shape[0]), first]
    return np.where(any_true, ranges_m[first], np.inf)


@dataclass(frozen=True)
class ObstacleDistanceInput:
    """What the feed needs each tick: the current costmap and the vehicle's map-frame pose."""

    costmap: Costmap
    xy_map_m: tuple[float, float]
    yaw_map_rad: float

    @classmethod
    def from_vehicle_state(cls, costmap: Costmap, state: VehicleState) -> "ObstacleDistanceInput | None":
        """Pose from PX4's telemetry, for a map whose origin is PX4's local NED origin
        (ENU axes); None until both position and attitude have been reported."""
        if state.position_ned_m is None or state.yaw_ned_rad is None:
            return None
        x_east, y_north, _ = ned_to_enu(*state.position_ned_m)
        return cls(costmap, (x_east, y_north), yaw_ned_to_enu(state.yaw_ned_rad))


class ObstacleDistanceFeed(BackgroundPart):
    """Sends OBSTACLE_DISTANCE at ``rate_hz`` from ``source()`` (async context manager).

    ``source`` returns the latest :class:`ObstacleDistanceInput`, or None when there is no
    map or pose yet (then nothing is sent, and PX4 sees the feed as absent).
    """

    def __init__(
        self,
        link: MavlinkLink,
        source: Callable[[], ObstacleDistanceInput | None],
        rate_hz: float = 10.0,
        *,
        min_distance_m: float = 0.2,
        max_distance_m: float = 8.0,
        unknown_is_obstacle: bool = False,
    ) -> None:
        if rate_hz <= 0.0:
            raise ValueError(f"obstacle distance rate must be > 0 Hz (got {rate_hz})")
        self.link = link
        self.source = source
        self.period_s = 1.0 / rate_hz
        self.min_distance_m = min_distance_m
        self.max_distance_m = max_distance_m
        self.unknown_is_obstacle = unknown_is_obstacle
        self.sent = 0
        self.errors = 0
        self.last_scan: ObstacleDistanceScan | None = None
        self._boot_s = time.monotonic()
        super().__init__()

    def _start(self) -> None:
        self._background.start(self._run(), name="obstacle-distance")

    async def _run(self) -> None:
        next_s = time.monotonic()
        while True:
            await self._tick()
            next_s += self.period_s
            now = time.monotonic()
            if now - next_s > self.period_s:
                next_s = now  # fell behind (e.g. a slow ray cast): restart the schedule
            await asyncio.sleep(max(0.0, next_s - now))

    async def _tick(self) -> None:
        try:
            inp = self.source()
            if inp is None:
                return
            scan = await asyncio.to_thread(
                compute_obstacle_distances, inp.costmap, inp.xy_map_m, inp.yaw_map_rad,
                min_distance_m=self.min_distance_m, max_distance_m=self.max_distance_m,
                unknown_is_obstacle=self.unknown_is_obstacle,
            )
        except Exception:
            # A bad map or pose must not stop the feed (or, through the task group, the
            # service): skip this scan, log the first failure and every 50th.
            self.errors += 1
            if self.errors == 1 or self.errors % 50 == 0:
                log.exception("obstacle distance: no scan from this input (%d failures)", self.errors)
            return
        if not self.link.is_open:
            return
        time_usec = int((time.monotonic() - self._boot_s) * 1e6)
        self.link.send(scan.to_message(self.link, time_usec))
        self.last_scan = scan
        self.sent += 1
