"""Cost values, the vertical band rule, object footprints and the combined costmap value.

Cost constants are named once here (nav2 ``costmap_2d`` style) and used everywhere:
``FREE_SPACE`` .. ``INSCRIBED_INFLATED_OBSTACLE`` are traversal costs, ``LETHAL_OBSTACLE``
is an obstacle cell, ``NO_INFORMATION`` is unknown. A :class:`Costmap` is the product of the
semantic map for one flight altitude; the planner consumes it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from semmap.errors import MapError
from semmap.grid import GridSpec, rasterize_polygon

FREE_SPACE = 0
#: Highest cost that is still traversable (soft costs live in 1..MAX_NON_OBSTACLE).
MAX_NON_OBSTACLE = 252
INSCRIBED_INFLATED_OBSTACLE = 253
LETHAL_OBSTACLE = 254
NO_INFORMATION = 255

#: Default e-folding distance of the cost beyond a keep-out zone (see :class:`Costmap`).
DEFAULT_CLEARANCE_DECAY_M = 0.15


@dataclass(frozen=True)
class VerticalBand:
    """The height interval the vehicle occupies (metres above the floor), margin included."""

    z_min_m: float
    z_max_m: float

    @classmethod
    def for_altitude(
        cls, altitude_m: float, vehicle_height_m: float, margin_m: float
    ) -> "VerticalBand":
        """altitude +- (half the vehicle height + margin)."""
        half = vehicle_height_m / 2.0 + margin_m
        return cls(altitude_m - half, altitude_m + half)

    def intersects(self, z_min_m: float, z_max_m: float) -> bool:
        return z_min_m <= self.z_max_m and z_max_m >= self.z_min_m


@dataclass(frozen=True, eq=False)
class ObjectFootprint:
    """What the costmap and planner need to know of one object, in the map frame.

    ``polygon_xy_m``: (M, 2) footprint polygon (the projection of the whole object, legs and
    the space between them included). ``z_min_m``/``z_max_m``: its vertical extent above the
    floor. ``existence``: probability the object is real (1.0 for ground truth).
    ``margin_m``: the keep-out distance around the footprint; None means its class's margin
    (filled in by :meth:`with_class_margin` where the classes are known), 0.0 means none.
    """

    object_id: int
    class_name: str
    polygon_xy_m: NDArray[np.float64]
    z_min_m: float
    z_max_m: float
    existence: float = 1.0
    margin_m: float | None = None

    def with_class_margin(self, class_margins_m: Mapping[str, float]) -> ObjectFootprint:
        """This footprint with its class's margin if it has none of its own (0 for a class
        ``class_margins_m`` does not list)."""
        if self.margin_m is not None:
            return self
        return replace(self, margin_m=float(class_margins_m.get(self.class_name, 0.0)))

    @property
    def resolved_margin_m(self) -> float:
        """The margin in metres, for code that paints or reports it after
        :meth:`with_class_margin`."""
        if self.margin_m is None:
            raise MapError(
                f"object {self.object_id} ({self.class_name}): margin_m is None (its class's "
                "margin), not yet resolved with ObjectFootprint.with_class_margin"
            )
        return self.margin_m

    def blocks(self, band: VerticalBand) -> bool:
        """True if the object's height range intersects the vehicle's band."""
        return band.intersects(self.z_min_m, self.z_max_m)

    def mask(self, spec: GridSpec) -> NDArray[np.bool_]:
        return rasterize_polygon(spec, self.polygon_xy_m)


@dataclass(frozen=True, eq=False)
class Costmap:
    """A combined costmap at one flight altitude.

    ``cost``: (rows, cols) uint8 with the constants above. ``class_index``: optional (rows,
    cols) int16, the most likely class per cell (-1 none) for pictures and reports.
    ``clearance_decay_m``: the distance over which cost decays by e beyond a keep-out zone;
    the map's margins were painted with it and the planner's proximity cost beyond the
    vehicle radius uses it, so one setting shapes both.
    """

    spec: GridSpec
    cost: NDArray[np.uint8]
    band: VerticalBand
    stamp_s: float = 0.0
    class_index: NDArray[np.int16] | None = None
    objects: tuple[ObjectFootprint, ...] = field(default_factory=tuple)
    clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M

    def __post_init__(self) -> None:
        if not self.clearance_decay_m > 0.0:
            raise ValueError(f"clearance_decay_m must be > 0 (got {self.clearance_decay_m})")
        if self.cost.shape != self.spec.shape_rc or self.cost.dtype != np.uint8:
            raise ValueError(
                f"cost must be uint8 of shape {self.spec.shape_rc}, got {self.cost.dtype} {self.cost.shape}"
            )

    @property
    def lethal(self) -> NDArray[np.bool_]:
        return self.cost == LETHAL_OBSTACLE

    @property
    def unknown(self) -> NDArray[np.bool_]:
        return self.cost == NO_INFORMATION

    def cost_at_xy(self, xy_m: NDArray[np.floating]) -> NDArray[np.uint8]:
        """Cost at (N, 2) map points; outside the grid counts as NO_INFORMATION."""
        rc = self.spec.cell_of(xy_m)
        inside = self.spec.contains_rc(rc)
        out = np.full(len(rc), NO_INFORMATION, dtype=np.uint8)
        out[inside] = self.cost[rc[inside, 0], rc[inside, 1]]
        return out
