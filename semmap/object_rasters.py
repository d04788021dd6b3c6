"""Per-object rasters shared by the object-derived costmap layers (:mod:`semmap.layers`).

Each object's footprint is rasterised once per change on the layers' grid, with the distance
field its safety margin decays over, so every layer and every frame reuses them; a footprint
the object map only refined by millimetres keeps its raster.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import DEFAULT_CLEARANCE_DECAY_M, ObjectFootprint
from semmap.errors import MapError
from semmap.grid import Bounds, GridSpec, rasterize_polygon

__all__ = ["ObjectRaster", "ObjectRasters"]


@dataclass(frozen=True, eq=False)
class ObjectRaster:
    """One object drawn on the grid: its footprint mask and distance field in a window.

    ``window``: cells covered (footprint bounding box grown by the margin's reach, clipped to
    the grid). ``mask``: (window rows, cols) bool footprint. ``dist_m``: (window rows, cols)
    float32 distance from the footprint in metres (0 inside). ``class_probs``: (K,) float32
    over the layer's class names.
    """

    footprint: ObjectFootprint
    class_probs: NDArray[np.float32]
    window: Bounds
    mask: NDArray[np.bool_]
    dist_m: NDArray[np.float32]

    def views(self, window: Bounds) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
        """(slices into this raster, slices into an array covering ``window``), or None if
        they do not overlap."""
        inter = Bounds(
            max(self.window.r0, window.r0), max(self.window.c0, window.c0),
            min(self.window.r1, window.r1), min(self.window.c1, window.c1),
        )
        if inter.is_empty:
            return None
        return (
            inter.shifted(-self.window.r0, -self.window.c0).slices,
            inter.shifted(-window.r0, -window.c0).slices,
        )


def _geometry_key(fp: ObjectFootprint) -> tuple[NDArray[np.float64], float]:
    return np.asarray(fp.polygon_xy_m, np.float64).reshape(-1, 2).copy(), fp.resolved_margin_m


def _same_geometry(drawn: tuple[NDArray[np.float64], float] | None, fp: ObjectFootprint, tol_m: float) -> bool:
    """The footprint is within ``tol_m`` (every vertex) of the one drawn, same margin."""
    if drawn is None:
        return False
    poly = np.asarray(fp.polygon_xy_m, np.float64).reshape(-1, 2)
    return (drawn[1] == fp.resolved_margin_m and drawn[0].shape == poly.shape
            and bool(np.all(np.abs(drawn[0] - poly) <= tol_m)))


class ObjectRasters:
    """Per-object rasters on the current grid, recomputed only for objects that changed.

    A footprint that moved by at most ``redraw_fraction`` of a cell (every vertex) since it
    was drawn keeps its raster: the object map refines footprints by millimetres each
    frame, which would not change the cells but would cost a redraw.
    """

    def __init__(
        self, class_names: Sequence[str], clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M,
        redraw_fraction: float = 0.25,
    ) -> None:
        self.class_names = list(class_names)
        self.clearance_decay_m = clearance_decay_m
        self.redraw_fraction = redraw_fraction
        self.spec: GridSpec | None = None
        self.rasters: dict[int, ObjectRaster] = {}
        #: The polygon and margin each raster was drawn from.
        self._geometry: dict[int, tuple[NDArray[np.float64], float]] = {}

    def reach_m(self, fp: ObjectFootprint) -> float:
        """How far beyond the footprint the margin layer may put cost."""
        return fp.resolved_margin_m + 3.0 * self.clearance_decay_m

    def one_hot(self, class_name: str) -> NDArray[np.float32]:
        """(K,) class probabilities of an object known only by its class name."""
        p = np.zeros(len(self.class_names), np.float32)
        if class_name in self.class_names:
            p[self.class_names.index(class_name)] = 1.0
        return p

    def set_spec(self, spec: GridSpec) -> Bounds:
        """Re-draw everything on a new grid (after growth); returns the whole grid if changed."""
        if spec == self.spec:
            return Bounds.empty()
        self.spec = spec
        old = list(self.rasters.values())
        self.rasters.clear()
        self._geometry.clear()
        for r in old:
            self.rasters[r.footprint.object_id] = self._draw(r.footprint, r.class_probs)
            self._geometry[r.footprint.object_id] = _geometry_key(r.footprint)
        return spec.bounds

    def update(
        self, objects: Sequence[ObjectFootprint],
        class_probs: Mapping[int, NDArray[np.floating]] | None = None,
    ) -> Bounds:
        """Replace the object set; returns the window of every added, changed or removed object."""
        if self.spec is None:
            raise MapError("ObjectRasters.update before set_spec")
        probs = class_probs or {}
        touched = Bounds.empty()
        seen: set[int] = set()
        for fp in objects:
            oid = fp.object_id
            if oid in seen:
                raise MapError(f"duplicate object id {oid} in one object update")
            seen.add(oid)
            cp = np.asarray(probs.get(oid, self.one_hot(fp.class_name)), np.float32).reshape(-1)
            if len(cp) != len(self.class_names):
                raise MapError(
                    f"object {oid}: {len(cp)} class probabilities for {len(self.class_names)} classes"
                )
            old = self.rasters.get(oid)
            tol = self.redraw_fraction * self.spec.resolution_m
            if old is not None and _same_geometry(self._geometry.get(oid), fp, tol):
                if not _same_semantics(old, fp, cp):
                    touched = touched.union(old.window)
                self.rasters[oid] = ObjectRaster(fp, cp, old.window, old.mask, old.dist_m)
                continue
            new = self._draw(fp, cp)
            self.rasters[oid] = new
            self._geometry[oid] = _geometry_key(fp)
            touched = touched.union(new.window)
            if old is not None:
                touched = touched.union(old.window)
        for oid in [o for o in self.rasters if o not in seen]:
            touched = touched.union(self.rasters.pop(oid).window)
            self._geometry.pop(oid, None)
        return touched

    def overlapping(self, window: Bounds) -> list[ObjectRaster]:
        """Rasters whose window meets ``window``, lowest existence first (so painters that
        take the last value favour the likelier object)."""
        out = [r for r in self.rasters.values() if r.views(window) is not None]
        return sorted(out, key=lambda r: r.footprint.existence)

    def _draw(self, fp: ObjectFootprint, class_probs: NDArray[np.float32]) -> ObjectRaster:
        import cv2  # local, as in semmap.grid

        spec = self.spec
        assert spec is not None
        poly = np.asarray(fp.polygon_xy_m, np.float64).reshape(-1, 2)
        reach = self.reach_m(fp) + spec.resolution_m
        lo = spec.cell_of((poly.min(axis=0) - reach)[None])[0]
        hi = spec.cell_of((poly.max(axis=0) + reach)[None])[0] + 1
        window = Bounds(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])).clipped(spec.shape_rc)
        if window.is_empty:
            empty = np.zeros((0, 0), bool)
            return ObjectRaster(fp, class_probs, window, empty, np.zeros((0, 0), np.float32))
        r = spec.resolution_m
        sub = GridSpec(
            r, (spec.origin_xy_m[0] + window.c0 * r, spec.origin_xy_m[1] + window.r0 * r),
            (window.r1 - window.r0, window.c1 - window.c0),
        )
        mask = rasterize_polygon(sub, poly)
        if np.any(mask):
            dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            dist_m = dist.astype(np.float32) * np.float32(r)
        else:
            dist_m = np.full(mask.shape, np.inf, np.float32)
        return ObjectRaster(fp, class_probs, window, mask, dist_m)


def _same_semantics(old: ObjectRaster, fp: ObjectFootprint, cp: NDArray[np.float32]) -> bool:
    o = old.footprint
    return (
        o.class_name == fp.class_name and o.z_min_m == fp.z_min_m and o.z_max_m == fp.z_max_m
        and o.existence == fp.existence and np.array_equal(old.class_probs, cp)
    )
