"""Semantic layers behind one small interface, combined into a costmap by a named rule.

The nav2 ``costmap_2d`` pattern: each layer is updated from its own input and reports the
window of cells it touched; :class:`LayeredCostmap` asks each layer for its costs inside the
union of touched windows and combines them with a named rule (see :data:`COMBINE_RULES`).
A layer answers ``NO_INFORMATION`` where it has no opinion, so "unknown" survives only where
no layer knows the cell. Every layer remembers when it was last updated, so a consumer can
refuse to plan on a stale map (:meth:`LayeredCostmap.stale_layers`).

Layers:

* :class:`OccupancyLayer` - the probability grid of the depth band scan.
* :class:`ObjectFootprintLayer` - whole footprints of objects whose height range meets the
  vehicle's band, costed by the object's existence probability.
* :class:`SafetyMarginLayer` - a per-class margin around those objects whose cost decays with
  distance (:func:`cost_decay`), scaled by existence.
* :class:`ClassProbabilityLayer` and :class:`HeightLayer` - per-cell semantic planes (class
  probabilities with a "none" plane, object top height); they add no cost.

The object-derived layers share one :class:`~semmap.object_rasters.ObjectRasters` cache,
so each object's polygon is rasterised (and its distance field computed) once per change,
not once per layer and frame.

This module is the one place that turns an object into cost: :func:`paint_objects` applies
the same footprint and margin layers to a costmap that did not come from the layer stack (a
ROS map with its objects, a ground-truth room), and the planner's proximity cost uses
:func:`cost_decay` with the costmap's ``clearance_decay_m``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import (
    DEFAULT_CLEARANCE_DECAY_M,
    FREE_SPACE,
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    MAX_NON_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    ObjectFootprint,
    VerticalBand,
)
from semmap.errors import MapError
from semmap.grid import Bounds, GridSpec
from semmap.object_rasters import ObjectRasters
from semmap.occupancy import ProbabilityGrid
from semmap.scan import BandScan


@runtime_checkable
class Layer(Protocol):
    """What :class:`LayeredCostmap` needs of a layer."""

    name: str
    #: Time of the last update (seconds, the frames' clock); -inf before the first.
    stamp_s: float
    #: Window touched by the last update, in the grid's current indices.
    last_bounds: Bounds

    def is_fresh(self, now_s: float, max_age_s: float) -> bool:
        """True if updated within ``max_age_s`` of ``now_s``."""
        ...

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> NDArray[np.uint8] | None:
        """(window rows, window cols) uint8 costs for ``band``, NO_INFORMATION where the layer
        has no opinion; None if the layer never contributes cost."""
        ...


class _Stamped:
    """Freshness bookkeeping shared by the concrete layers."""

    name = "layer"

    def __init__(self) -> None:
        self.stamp_s = float("-inf")
        self.last_bounds = Bounds.empty()

    def is_fresh(self, now_s: float, max_age_s: float) -> bool:
        return now_s - self.stamp_s <= max_age_s

    def _touch(self, stamp_s: float, bounds: Bounds) -> Bounds:
        self.stamp_s = max(self.stamp_s, float(stamp_s))
        self.last_bounds = bounds
        return bounds


class OccupancyLayer(_Stamped):
    """Costs from the probability grid: lethal at or above ``occupied_threshold``, free at or
    below ``free_threshold``, a linear soft cost in between, NO_INFORMATION where unobserved.

    The grid is built from the scan band chosen when mapping; the ``band`` of a costmap query
    does not re-slice it (objects carry the height information that does).
    """

    name = "occupancy"

    def __init__(
        self, grid: ProbabilityGrid, occupied_threshold: float = 0.6, free_threshold: float = 0.5,
    ) -> None:
        super().__init__()
        if not 0.0 < free_threshold < occupied_threshold < 1.0:
            raise MapError(
                f"need 0 < free_threshold < occupied_threshold < 1 (got {free_threshold}, {occupied_threshold})"
            )
        self.grid = grid
        self.occupied_threshold = occupied_threshold
        self.free_threshold = free_threshold
        p = grid.tables.value_to_probability.astype(np.float64)
        soft = (p - free_threshold) / (occupied_threshold - free_threshold)
        lut = np.rint(np.clip(soft, 0.0, 1.0) * MAX_NON_OBSTACLE)
        lut = np.where(p >= occupied_threshold, LETHAL_OBSTACLE, lut)
        lut = np.where(p <= free_threshold, FREE_SPACE, lut)
        lut[0] = NO_INFORMATION
        #: (32768,) uint8 cost of every grid value.
        self.cost_lut = lut.astype(np.uint8)

    def update(self, scan: BandScan) -> Bounds:
        """Insert one band scan into the grid; returns the touched window."""
        bounds = self.grid.insert_scan(
            scan.origin_xy_m, scan.near_xy_m, scan.far_xy_m, scan.hit_xy_m, scan.is_hit, scan.valid
        )
        return self._touch(scan.stamp_s, bounds)

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> NDArray[np.uint8]:
        _check_spec(spec, self.grid.spec)
        return self.cost_lut[self.grid.values[window.slices]]


def _check_spec(spec: GridSpec, own: GridSpec) -> None:
    if spec != own:
        raise MapError(f"layer grid {own} differs from the costmap grid {spec}")


# --- objects ------------------------------------------------------------------------------

def _paint_max(out: NDArray[np.uint8], where: NDArray[np.bool_], value: NDArray[np.uint8] | int) -> None:
    """out[where] = max(out, value), treating NO_INFORMATION in ``out`` as 'nothing yet'."""
    v = np.broadcast_to(np.asarray(value, np.uint8), out.shape)
    cur = out[where]
    new = v[where]
    out[where] = np.where(cur == NO_INFORMATION, new, np.maximum(cur, new))


#: A cell this close to an object's class margin counts as inside it: distance fields in
#: float32 put a cell exactly at the margin a hair beyond it.
MARGIN_TOLERANCE_M = 1e-6


def cost_decay(beyond_m: NDArray[np.floating] | float, decay_m: float) -> NDArray[np.float64]:
    """Cost fraction 0..1 at ``beyond_m`` metres outside a keep-out zone: 1 at its edge (and
    inside), falling by e every ``decay_m`` (nav2's inflation curve)."""
    return np.exp(-np.maximum(np.asarray(beyond_m, np.float64), 0.0) / decay_m)


def existence_scale(existence: float, confirm: float) -> float:
    """1 once an object is confirmed, else its existence probability."""
    return 1.0 if existence >= confirm else float(np.clip(existence, 0.0, 1.0))


def existence_cost(existence: float, confirm: float) -> int:
    """Cost of a footprint cell: lethal once the object is confirmed, else scaled by existence."""
    if existence >= confirm:
        return LETHAL_OBSTACLE
    return int(round(existence_scale(existence, confirm) * MAX_NON_OBSTACLE))


class _ObjectLayer(_Stamped):
    """Base of the layers drawn from the shared object rasters."""

    def __init__(self, rasters: ObjectRasters) -> None:
        super().__init__()
        self.rasters = rasters

    def mark_updated(self, stamp_s: float, bounds: Bounds) -> Bounds:
        """Record that the shared rasters changed in ``bounds`` at ``stamp_s``."""
        return self._touch(stamp_s, bounds)

    def update(
        self, objects: Sequence[ObjectFootprint], stamp_s: float,
        class_probs: Mapping[int, NDArray[np.floating]] | None = None,
    ) -> Bounds:
        """Take the current objects; returns the touched window. When several layers share
        the rasters, :meth:`LayeredCostmap.update_objects` updates them once for all."""
        return self._touch(stamp_s, self.rasters.update(objects, class_probs))


class ObjectFootprintLayer(_ObjectLayer):
    """Whole footprints (legs and the space between) of objects that block the band, costed
    by existence (lethal once confirmed)."""

    name = "objects"

    def __init__(self, rasters: ObjectRasters, existence_confirm: float = 0.6) -> None:
        super().__init__(rasters)
        self.existence_confirm = existence_confirm

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> NDArray[np.uint8]:
        out = np.full((window.r1 - window.r0, window.c1 - window.c0), NO_INFORMATION, np.uint8)
        for r in self.rasters.overlapping(window):
            views = r.views(window)
            if views is None or not r.footprint.blocks(band):
                continue
            src, dst = views
            c = existence_cost(r.footprint.existence, self.existence_confirm)
            _paint_max(out[dst], r.mask[src], c)
        return out


class SafetyMarginLayer(_ObjectLayer):
    """A margin around blocking objects: within the class margin the cost is
    INSCRIBED_INFLATED_OBSTACLE, beyond it decays as ``exp(-(d - margin) / decay)``; all of
    it scaled by the object's existence. No opinion beyond three decay lengths."""

    name = "margin"

    def __init__(self, rasters: ObjectRasters, existence_confirm: float = 0.6) -> None:
        super().__init__(rasters)
        self.existence_confirm = existence_confirm

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> NDArray[np.uint8]:
        out = np.full((window.r1 - window.r0, window.c1 - window.c0), NO_INFORMATION, np.uint8)
        decay = self.rasters.clearance_decay_m
        for r in self.rasters.overlapping(window):
            views = r.views(window)
            if views is None or not r.footprint.blocks(band):
                continue
            src, dst = views
            d = r.dist_m[src]
            m = r.footprint.resolved_margin_m
            scale = existence_scale(r.footprint.existence, self.existence_confirm)
            soft = MAX_NON_OBSTACLE * cost_decay(d - m, decay)
            # A cell exactly at the margin is inside it (the safe side of float rounding).
            cost = np.where(d <= m + MARGIN_TOLERANCE_M, float(INSCRIBED_INFLATED_OBSTACLE), soft) * scale
            cost_u8 = np.rint(cost).astype(np.uint8)
            _paint_max(out[dst], (d <= self.rasters.reach_m(r.footprint)) & (cost_u8 > 0), cost_u8)
        return out


class ClassProbabilityLayer(_ObjectLayer):
    """Per-cell class probabilities: plane 0 is "no object", planes 1..K the classes.

    An object cell of existence ``e`` and class probabilities ``p`` has ``e * p_k`` for class
    k (the largest over overlapping objects) and the rest for "no object"; an observed cell
    without objects is "no object" for certain; an unobserved one is all zero (unknown).
    Stored quantised as uint8 (255 = 1) because a 50 m map at 5 cm has a million cells.
    """

    name = "classes"

    def __init__(self, rasters: ObjectRasters, grid: ProbabilityGrid | None = None) -> None:
        super().__init__(rasters)
        self.grid = grid

    @property
    def class_names(self) -> list[str]:
        return self.rasters.class_names

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> None:
        return None

    def probabilities(self, spec: GridSpec, window: Bounds | None = None) -> NDArray[np.uint8]:
        """(K + 1, window rows, window cols) uint8, 0..255 for 0..1 (see the class docstring)."""
        w = window or spec.bounds
        k = len(self.class_names)
        planes = np.zeros((k + 1, w.r1 - w.r0, w.c1 - w.c0), np.uint8)
        if self.grid is not None:
            _check_spec(spec, self.grid.spec)
            planes[0][self.grid.known[w.slices]] = 255
        for r in self.rasters.overlapping(w):
            views = r.views(w)
            if views is None:
                continue
            src, dst = views
            m = r.mask[src]
            e = float(np.clip(r.footprint.existence, 0.0, 1.0))
            q = np.rint(e * r.class_probs * 255.0).astype(np.uint8)  # (K,)
            for i in range(k):
                plane = planes[i + 1][dst]
                plane[m] = np.maximum(plane[m], q[i])
        objects = planes[1:].astype(np.int32).sum(axis=0)
        covered = objects > 0
        planes[0][covered] = np.clip(255 - objects[covered], 0, 255).astype(np.uint8)
        return planes

    def class_index(self, spec: GridSpec, window: Bounds | None = None) -> NDArray[np.int16]:
        """(window rows, cols) int16 index into ``class_names`` of the likeliest class where
        some object covers the cell, -1 elsewhere."""
        planes = self.probabilities(spec, window)[1:]
        idx = np.argmax(planes, axis=0).astype(np.int16)
        idx[planes.max(axis=0) == 0] = -1
        return idx


class HeightLayer(_ObjectLayer):
    """Per-cell top height (map z, metres above the floor) of the tallest object there."""

    name = "height"

    def costs(self, spec: GridSpec, band: VerticalBand, window: Bounds) -> None:
        return None

    def heights_m(self, spec: GridSpec, window: Bounds | None = None) -> NDArray[np.float32]:
        """(window rows, cols) float32 metres; NaN where no object."""
        w = window or spec.bounds
        out = np.full((w.r1 - w.r0, w.c1 - w.c0), np.nan, np.float32)
        for r in self.rasters.overlapping(w):
            views = r.views(w)
            if views is None:
                continue
            src, dst = views
            region = out[dst]
            m = r.mask[src]
            region[m] = np.fmax(region[m], np.float32(r.footprint.z_max_m))
        return out


# --- combination --------------------------------------------------------------------------

def combine_maximum(costs: Sequence[NDArray[np.uint8]]) -> NDArray[np.uint8]:
    """The largest known cost per cell; NO_INFORMATION only where no layer knows the cell."""
    out = np.full(costs[0].shape, NO_INFORMATION, np.uint8)
    for c in costs:
        _paint_max(out, c != NO_INFORMATION, c)
    return out


def combine_overwrite(costs: Sequence[NDArray[np.uint8]]) -> NDArray[np.uint8]:
    """Later layers overwrite earlier ones where they know the cell (nav2 ``updateWithOverwrite``)."""
    out = np.full(costs[0].shape, NO_INFORMATION, np.uint8)
    for c in costs:
        known = c != NO_INFORMATION
        out[known] = c[known]
    return out


#: Named rules for combining layer costs, in layer order.
COMBINE_RULES: dict[str, Callable[[Sequence[NDArray[np.uint8]]], NDArray[np.uint8]]] = {
    "maximum": combine_maximum,
    "overwrite": combine_overwrite,
}


class LayeredCostmap:
    """The layer stack over one probability grid; produces :class:`Costmap` per band.

    Keeps the last combined costmap and recomputes only the windows layers touched since,
    unless the band or the grid changed.
    """

    def __init__(
        self, grid: ProbabilityGrid, class_names: Sequence[str], *, rule: str = "maximum",
        occupied_threshold: float = 0.6, free_threshold: float = 0.5,
        existence_confirm: float = 0.6, clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M,
    ) -> None:
        if rule not in COMBINE_RULES:
            raise MapError(f"unknown combination rule {rule!r} (known: {sorted(COMBINE_RULES)})")
        self.rule = rule
        self.grid = grid
        self.rasters = ObjectRasters(class_names, clearance_decay_m)
        self.rasters.set_spec(grid.spec)
        self.occupancy = OccupancyLayer(grid, occupied_threshold, free_threshold)
        self.footprints = ObjectFootprintLayer(self.rasters, existence_confirm)
        self.margins = SafetyMarginLayer(self.rasters, existence_confirm)
        self.classes = ClassProbabilityLayer(self.rasters, grid)
        self.heights = HeightLayer(self.rasters)
        self.layers: list[Layer] = [self.occupancy, self.footprints, self.margins, self.classes, self.heights]
        self._object_layers: list[_ObjectLayer] = [self.footprints, self.margins, self.classes, self.heights]
        self._dirty = Bounds.empty()
        self._cached: tuple[GridSpec, VerticalBand, NDArray[np.uint8], NDArray[np.int16]] | None = None

    @property
    def spec(self) -> GridSpec:
        return self.grid.spec

    def sync_spec(self) -> None:
        """Follow the grid after it grew or was replaced (object rasters redrawn, cache dropped)."""
        grew = self.rasters.set_spec(self.grid.spec)
        if not grew.is_empty:
            self._cached = None
            self._dirty = Bounds.empty()

    def update_scan(self, scan: BandScan) -> Bounds:
        """Insert a band scan (the grid may grow); returns the touched window."""
        bounds = self.occupancy.update(scan)
        self.sync_spec()
        self._dirty = self._dirty.union(bounds)
        return bounds

    def update_objects(
        self, objects: Sequence[ObjectFootprint], stamp_s: float,
        class_probs: Mapping[int, NDArray[np.floating]] | None = None,
    ) -> Bounds:
        """Replace the object set of every object layer at once; returns the touched window."""
        self.sync_spec()
        bounds = self.rasters.update(objects, class_probs)
        for layer in self._object_layers:
            layer.mark_updated(stamp_s, bounds)
        self._dirty = self._dirty.union(bounds)
        return bounds

    def stale_layers(self, now_s: float, max_age_s: float) -> list[str]:
        """Names of layers not updated within ``max_age_s`` of ``now_s``."""
        return [layer.name for layer in self.layers if not layer.is_fresh(now_s, max_age_s)]

    def combined(self, band: VerticalBand, window: Bounds) -> NDArray[np.uint8]:
        """(window rows, cols) combined cost of every cost-bearing layer in ``window``."""
        parts = [c for c in (layer.costs(self.spec, band, window) for layer in self.layers) if c is not None]
        return COMBINE_RULES[self.rule](parts)

    def costmap(self, band: VerticalBand) -> Costmap:
        """The combined :class:`Costmap` for a vehicle band; its ``stamp_s`` is the oldest
        layer stamp, so a consumer judging freshness by it is conservative."""
        self.sync_spec()
        spec = self.spec
        c = self._cached
        if c is None or c[0] != spec or c[1] != band:
            window = spec.bounds
            cost = np.empty(spec.shape_rc, np.uint8)
            cls = np.empty(spec.shape_rc, np.int16)
        else:
            window = self._dirty.clipped(spec.shape_rc)
            cost, cls = c[2], c[3]
        if not window.is_empty:
            cost[window.slices] = self.combined(band, window)
            cls[window.slices] = self.classes.class_index(spec, window)
        self._cached = (spec, band, cost, cls)
        self._dirty = Bounds.empty()
        stamps = [layer.stamp_s for layer in self.layers if np.isfinite(layer.stamp_s)]
        objects = tuple(r.footprint for r in self.rasters.rasters.values())
        return Costmap(
            spec, cost.copy(), band, stamp_s=min(stamps) if stamps else 0.0,
            class_index=cls.copy(), objects=objects, clearance_decay_m=self.rasters.clearance_decay_m,
        )

    def nbytes(self) -> int:
        """Bytes held by the grid, the cached costmap and the object rasters."""
        n = self.grid.values.nbytes
        if self._cached is not None:
            n += self._cached[2].nbytes + self._cached[3].nbytes
        for r in self.rasters.rasters.values():
            n += r.mask.nbytes + r.dist_m.nbytes
        return n


def paint_objects(
    base: Costmap, objects: Sequence[ObjectFootprint], band: VerticalBand, *,
    existence_confirm: float = 0.6, class_names: Sequence[str] = (),
    class_margins_m: Mapping[str, float] | None = None,
) -> Costmap:
    """``base`` with the footprint and margin layers of ``objects`` at ``band`` combined in by
    the maximum rule, as :class:`LayeredCostmap` combines them for the map's own objects.

    For a costmap that did not come from the layer stack: an occupancy map read from a file
    plus its objects, or a ground-truth room. Objects at or above ``existence_confirm`` are
    lethal with an inscribed margin; the margins decay over ``base.clearance_decay_m``. The
    result carries ``band`` and all of ``objects``, those whose margin is None given their
    class's from ``class_margins_m`` (none for a class it does not list).
    """
    objects = [fp.with_class_margin(class_margins_m or {}) for fp in objects]
    spec = base.spec
    rasters = ObjectRasters(class_names, base.clearance_decay_m)
    rasters.set_spec(spec)
    # Ids are the caller's business (files and tests reuse them); the rasters need them unique.
    rasters.update([dataclasses.replace(fp, object_id=i) for i, fp in enumerate(objects)])
    window = spec.bounds
    layers = (ObjectFootprintLayer(rasters, existence_confirm), SafetyMarginLayer(rasters, existence_confirm))
    cost = combine_maximum([base.cost, *(layer.costs(spec, band, window) for layer in layers)])
    return Costmap(
        spec, cost, band, stamp_s=base.stamp_s, class_index=base.class_index, objects=tuple(objects),
        clearance_decay_m=base.clearance_decay_m,
    )
