"""What the service tells the ground station and systemd while it runs.

:class:`StatusPublisher` sends telemetry at ``service.telemetry_rate_hz`` and, at
``service.status_rate_hz``, the status (state, stage timings, health), the objects when their
number changed and the flight-band costmap; it pings the systemd watchdog and keeps the
ground link's goal fence on the map's extent.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Callable

from companion.config import CompanionConfig
from companion.ground import MqttBridge
from companion.mavlink.vehicle import Vehicle
from companion.service.latency import LatencyStats
from companion.service.mission_runner import MissionRunner, position_enu
from companion.service.perception_process import PerceptionProcess
from companion.service.position_source import ServiceLocalization
from companion.systemd_notify import SystemdNotifier, Watchdog
from semmap.errors import CompanionError
from semmap.frames import ned_to_enu, yaw_ned_to_enu
from semmap.grid import GridSpec


class StatusPublisher:
    """The service's telemetry, status, objects and map on the ground link.

    ``state``: the service's lifecycle state now; ``map_spec``: the map's grid when the
    perception process has not reported one yet; ``started_at``: the service's start on
    ``time.monotonic`` (the status's uptime counts from it).
    """

    def __init__(self, cfg: CompanionConfig, vehicle: Vehicle, ground: MqttBridge, perception: PerceptionProcess,
                 runner: MissionRunner, localization: ServiceLocalization, notifier: SystemdNotifier, *,
                 state: Callable[[], str], map_spec: GridSpec, started_at: float) -> None:
        self.cfg = cfg
        self.vehicle = vehicle
        self.ground = ground
        self.perception = perception
        self.runner = runner
        self.localization = localization
        self.notifier = notifier
        self._state = state
        self._map_spec = map_spec
        self._t0 = started_at

    async def run(self, watchdog: Watchdog) -> None:
        """Publish until cancelled; each pass pings ``watchdog``'s ``status-loop``."""
        v, ground, perception = self.vehicle, self.ground, self.perception
        period = 1.0 / self.cfg.service.telemetry_rate_hz
        status_every = max(1, round(self.cfg.service.telemetry_rate_hz / self.cfg.service.status_rate_hz))
        n_objects = -1
        k = 0
        while True:
            watchdog.alive("status-loop")
            s = v.snapshot()
            pos = position_enu(s)
            if pos is not None:
                vel_enu_m_s = ned_to_enu(*(s.velocity_ned_m_s or (0.0, 0.0, 0.0)))
                yaw = yaw_ned_to_enu(s.yaw_ned_rad) if s.yaw_ned_rad is not None else 0.0
                ground.publish_telemetry(pos, vel_enu_m_s, yaw, s.armed, s.in_air,
                                         s.flight_mode.name if s.flight_mode else "UNKNOWN",
                                         None if s.battery_remaining is None else 100.0 * s.battery_remaining)
            if k % status_every == 0:
                state = self._state()
                health = {"mavlink": v.connected, "camera": perception.is_fresh(),
                          "map_fresh": perception.is_fresh(), "perception": perception.running,
                          "ground": ground.connected, **self.localization.health()}
                detail = f"offboard {v.offboard.state.value}, {perception.counters()['processed']} frames"
                if self.localization.enabled:
                    detail += f"; {self.localization.detail()}"
                ground.publish_status(state, time.monotonic() - self._t0, self.timings_ms(), health, detail)
                self.notifier.status(f"{state}: {detail}")
                self.update_goal_fence()
                objects = perception.objects
                if len(objects) != n_objects:
                    n_objects = len(objects)
                    ground.publish_objects(objects)
                with contextlib.suppress(CompanionError):
                    ground.publish_map(perception.costmap())
            k += 1
            await asyncio.sleep(period)

    def timings_ms(self) -> dict[str, float]:
        """The status message's ``stage_timings_ms``: the latest frame's ``detect``, ``track``,
        ``geometry``, ``grid``; the latest ``plan``; the latest end-to-end ``frame_to_map`` and
        ``frame_to_setpoint`` and their 95th percentiles so far (``*_p95``; see
        :meth:`~companion.service.app.CompanionService.latency_summary` for the definitions)."""
        timings: dict[str, float] = {}
        p = self.perception
        if p.latest is not None:
            timings.update(p.latest.timings_ms)
        if self.runner.last_plan_ms is not None:
            timings["plan"] = self.runner.last_plan_ms
        lat = {"frame_to_map": p.frame_to_map_ms, "frame_to_setpoint": self.runner.frame_to_setpoint_ms}
        for name, values in lat.items():
            if values:
                timings[name] = values[-1]
                p95 = LatencyStats(values).summary().get("p95_ms")
                if p95 is not None:
                    timings[f"{name}_p95"] = float(p95)
        return {n: round(t, 2) for n, t in timings.items() if math.isfinite(t)}

    def update_goal_fence(self) -> None:
        """Goals over MQTT must lie in the map (when no geofence is configured): tell the
        ground link's validator the map's current extent (the grid may grow)."""
        spec = self.perception.spec if self.perception.spec else self._map_spec
        x0, y0 = spec.origin_xy_m
        self.ground.validator.set_map_extent((x0, y0, x0 + spec.cols * spec.resolution_m,
                                              y0 + spec.rows * spec.resolution_m))
