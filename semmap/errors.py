"""The project's one exception tree.

It lives in ``semmap`` because ``semmap`` is the lowest package: ``planner`` and ``companion``
import it, never the other way round. ``companion.errors`` re-exports every class so service
code can ``from companion.errors import LinkError``.

Third-party exceptions are converted where they enter (``raise LinkError(...) from exc``) so
callers only ever catch ``CompanionError`` subclasses.
"""

from __future__ import annotations


class CompanionError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(CompanionError):
    """A configuration file or value is invalid. The message names the file and key path."""


class DataError(CompanionError):
    """Input data (a frame, a recorded file, a map file) is missing or corrupt."""


class FrameError(DataError):
    """A camera frame could not be read or is malformed. The message names the source."""


class PerceptionError(CompanionError):
    """Detector or tracker failure (bad model file, unknown output layout)."""


class MapError(CompanionError):
    """The semantic map could not be updated, saved or loaded."""


class PlanningError(CompanionError):
    """The planner could not produce a path (see the reason attribute where set)."""


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
