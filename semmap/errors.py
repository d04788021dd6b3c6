"""The root of the project's one exception tree, and the errors of mapping and planning.

The root, :class:`CompanionError`, lives in ``semmap`` because ``semmap`` is the lowest package:
``planner`` and ``companion`` import it, never the other way round. Errors of the link, the
mission, the ground link and the simulator are defined where those live, in
:mod:`companion.errors`, which also re-exports these so service code imports every error from
one place.

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
