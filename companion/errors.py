"""The companion's errors, in the project's one exception tree (root: :class:`CompanionError`).

The link, mission, ground-link and simulator errors are defined here, where those concepts
live; the root and the mapping and planning errors are :mod:`semmap.errors`'s, re-exported so
companion code imports every error from this module.
"""

from __future__ import annotations

from semmap.errors import (
    CompanionError,
    ConfigError,
    DataError,
    FrameError,
    MapError,
    PerceptionError,
    PlanningError,
)

__all__ = [
    "CommandError",
    "CompanionError",
    "ConfigError",
    "DataError",
    "FrameError",
    "GroundLinkError",
    "LinkError",
    "MapError",
    "MissionError",
    "PerceptionError",
    "PlanningError",
    "SimulationError",
]


class LinkError(CompanionError):
    """The MAVLink link failed: bad URL, socket error, malformed message."""


class CommandError(LinkError):
    """An autopilot command was rejected or timed out.

    ``result`` carries the MAVLink ``MAV_RESULT`` name (e.g. ``"DENIED"``) or ``"TIMEOUT"``.
    """

    def __init__(self, message: str, result: str = "UNKNOWN") -> None:
        super().__init__(message)
        self.result = result


class MissionError(LinkError):
    """A mission could not be uploaded, downloaded or parsed; names the failing item."""


class GroundLinkError(CompanionError):
    """The MQTT ground link failed or received an invalid command."""


class SimulationError(CompanionError):
    """The simulated world was asked for something it cannot do."""
