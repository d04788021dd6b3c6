"""Re-export of the project's exception tree (defined in :mod:`semmap.errors`)."""

from semmap.errors import (
    CommandError,
    CompanionError,
    ConfigError,
    DataError,
    FrameError,
    GroundLinkError,
    LinkError,
    MapError,
    MissionError,
    PerceptionError,
    PlanningError,
    SimulationError,
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
