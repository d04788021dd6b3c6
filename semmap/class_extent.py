"""Whether a mapped object's measured extent allows its class's margin and least footprint.

A class's safety margin and least footprint (:class:`~semmap.config.ClassConfig`) describe
objects of that class: a table top the depth slice misses, a conference table mapped short
from one side. An object that stands far taller than anything of its class (a 1.7 m cabinet
the detector called a chair or a conference table) is not of that class, whatever the votes
say: its measured footprint still blocks, but growing it to a conference table's size or
ringing it with a chair's margin paints space the vehicle saw free and closes real passages.
"""

from __future__ import annotations

from semmap.config import ClassConfig

__all__ = [
    "HEIGHT_ALLOWANCE_M", "MEASURED_ONLY_MARGIN_M", "ON_TOP_ALLOWANCE_M", "class_height_limit_m",
    "contradicts_class",
]

#: What may stand on a table's top and join its cluster (a monitor, a lamp, a vase).
ON_TOP_ALLOWANCE_M = 0.6
#: Margin of an object its class does not fit: only the error of a measured footprint's edge.
MEASURED_ONLY_MARGIN_M = 0.05
#: Measurement slack above the class's height range for objects nothing stands on.
HEIGHT_ALLOWANCE_M = 0.15


def class_height_limit_m(cls: ClassConfig) -> float | None:
    """The highest point an object of ``cls`` may measure, or None when the class states no
    height range."""
    if cls.prior is None or cls.prior.height_m is None:
        return None
    allowance = ON_TOP_ALLOWANCE_M if cls.shape == "table" else HEIGHT_ALLOWANCE_M
    return cls.prior.height_m[1] + allowance


def contradicts_class(cls: ClassConfig, z_max_m: float) -> bool:
    """True when an object whose highest point is ``z_max_m`` above the floor cannot be of
    ``cls``."""
    limit = class_height_limit_m(cls)
    return limit is not None and z_max_m > limit
