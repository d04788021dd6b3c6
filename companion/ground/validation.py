"""Limits every ground command must pass before it can reach the vehicle.

Order of checks (the first failure is the reason sent back): rate limit (a token bucket, so
a flood of commands - valid or not - cannot keep the link busy), schema
(:func:`companion.ground.schema.parse_command`), then the configured limits: goals must lie
inside the geofence (``planner.geofence_xy_m``, or the map's extent when that is None) and
below ``planner.max_altitude_m``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from companion.config import MqttConfig
from companion.ground.schema import Command, GoalCommand, Rejection, parse_command, peek_request_id
from planner.config import PlannerConfig
from semmap.errors import ConfigError


class TokenBucket:
    """``rate_hz`` tokens per second, at most ``burst`` saved up; one token per command."""

    def __init__(
        self, rate_hz: float, burst: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if rate_hz <= 0.0 or burst < 1:
            raise ValueError(f"rate_hz must be > 0 and burst >= 1 (got {rate_hz}, {burst})")
        self.rate_hz = rate_hz
        self.burst = burst
        self._clock = clock
        self._tokens = float(burst)
        self._last_s = clock()

    def try_take(self) -> bool:
        """Take one token if there is one; False means the caller is over the rate."""
        now = self._clock()
        self._tokens = min(float(self.burst), self._tokens + (now - self._last_s) * self.rate_hz)
        self._last_s = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


def _check_fence(fence: tuple[float, float, float, float], source: str) -> None:
    x_min, y_min, x_max, y_max = fence
    if not all(math.isfinite(v) for v in fence) or x_min >= x_max or y_min >= y_max:
        raise ConfigError(
            f"{source}: must be [x_min, y_min, x_max, y_max] with x_min < x_max and "
            f"y_min < y_max (got {list(fence)})"
        )


class CommandValidator:
    """Turns raw command payloads into commands the service may act on, or rejections.

    ``geofence_xy_m``: [x_min, y_min, x_max, y_max] in the map frame (metres), or None to
    use the map's extent (see :meth:`set_map_extent`); with neither, goals are refused.
    ``max_altitude_m``: highest goal altitude above the floor. ``clock``: monotonic seconds
    (injectable for tests).
    """

    def __init__(
        self,
        *,
        geofence_xy_m: tuple[float, float, float, float] | None,
        max_altitude_m: float,
        rate_limit_hz: float,
        burst: int,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if geofence_xy_m is not None:
            _check_fence(geofence_xy_m, "geofence_xy_m")
        if not max_altitude_m > 0.0:
            raise ConfigError(f"max_altitude_m: must be > 0 (got {max_altitude_m})")
        self.geofence_xy_m = geofence_xy_m
        self.max_altitude_m = max_altitude_m
        self._map_extent_xy_m: tuple[float, float, float, float] | None = None
        self._bucket = TokenBucket(rate_limit_hz, burst, clock)

    @classmethod
    def from_config(
        cls, planner: PlannerConfig, mqtt: MqttConfig, clock: Callable[[], float] = time.monotonic
    ) -> "CommandValidator":
        """The validator for a configuration: planner limits, MQTT rate limit."""
        if planner.geofence_xy_m is not None:
            _check_fence(planner.geofence_xy_m, "planner.geofence_xy_m")
        return cls(
            geofence_xy_m=planner.geofence_xy_m,
            max_altitude_m=planner.max_altitude_m,
            rate_limit_hz=mqtt.command_rate_limit_hz,
            burst=mqtt.command_burst,
            clock=clock,
        )

    def set_map_extent(self, extent_xy_m: tuple[float, float, float, float] | None) -> None:
        """The map's (x_min, y_min, x_max, y_max), used as the fence when none is configured."""
        if extent_xy_m is not None:
            _check_fence(extent_xy_m, "map extent")
        self._map_extent_xy_m = extent_xy_m

    @property
    def fence_xy_m(self) -> tuple[float, float, float, float] | None:
        """The fence in force: the configured one, else the map's extent, else None."""
        return self.geofence_xy_m if self.geofence_xy_m is not None else self._map_extent_xy_m

    def check_limits(self, cmd: Command) -> str | None:
        """The reason ``cmd`` breaks a configured limit, or None if it is within them."""
        if not isinstance(cmd, GoalCommand):
            return None
        if cmd.altitude_m is not None and cmd.altitude_m > self.max_altitude_m:
            return f"goal.altitude_m: must be <= {self.max_altitude_m} (got {cmd.altitude_m})"
        fence = self.fence_xy_m
        if fence is None:
            return "goal: no geofence configured and no map extent known yet"
        x_min, y_min, x_max, y_max = fence
        if not x_min <= cmd.x_m <= x_max:
            return f"goal.x_m: {cmd.x_m} is outside the geofence x in [{x_min}, {x_max}] m"
        if not y_min <= cmd.y_m <= y_max:
            return f"goal.y_m: {cmd.y_m} is outside the geofence y in [{y_min}, {y_max}] m"
        return None

    def validate(self, kind: str, payload: bytes | bytearray | str) -> Command | Rejection:
        """Rate limit, parse and check one payload received on ``cmd/<kind>``. Never raises."""
        if not self._bucket.try_take():
            return Rejection(
                kind,
                f"rate limited: more than {self._bucket.rate_hz:g} commands/s "
                f"(burst {self._bucket.burst})",
                peek_request_id(payload),
            )
        parsed = parse_command(kind, payload)
        if isinstance(parsed, Rejection):
            return parsed
        reason = self.check_limits(parsed)
        if reason is not None:
            return Rejection(kind, reason, parsed.request_id)
        return parsed

