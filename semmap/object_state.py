"""One object of the object map: its mutable state while fused, and its immutable snapshot.

:class:`ObjectState` is what :class:`semmap.objects.ObjectMap` updates per observation (class
probabilities, existence log-odds, position, hull, height history, footprint evidence);
:class:`MappedObject` is what the map reports. Both are plain data with no association logic.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semmap.camera_view import EdgeDirections
from semmap.class_prior import ClassPrior
from semmap.config import MapConfig
from semmap.costmap import ObjectFootprint
from semmap.errors import MapError
from semmap.object_evidence import FootprintEvidence
from semmap.polygons import (
    convex_footprint,
    convex_intersection,
    grow_to_least_size,
    min_perimeter_rectangle,
    polygon_area_m2,
)

__all__ = ["HISTORY", "MIN_CLASS_PROB", "MISS_INTERVAL_S", "MISS_STEP_M", "MISS_TURN_DEG", "MappedObject",
           "ObjectState", "consistent", "logit", "overlaps", "quantile", "sigmoid"]

#: Observations kept per object for the robust height estimate.
HISTORY = 30
#: Class probabilities never drop below this, so a later majority can still win.
MIN_CLASS_PROB = 1e-4
#: Misses of one object closer together than this (seconds) count as one view between them:
#: consecutive frames from nearly the same place miss for the same reason (a thin desk top
#: edge-on, a box the detector does not take), so counted per frame at 15-30 Hz they erase a
#: well-seen object within a second.
MISS_INTERVAL_S = 0.5
#: ... unless the camera moved this far (metres) or turned this much (degrees) since the last
#: counted miss: then it is another view, whatever the time (keyframes, a fast survey). A
#: drone at 0.5 m/s covers this in the interval above, so video counts as before.
MISS_STEP_M = 0.25
MISS_TURN_DEG = 15.0


def quantile(values: Iterable[float], q: float) -> float:
    """Linear-interpolated quantile of a short sequence (plain Python: a few dozen values)."""
    v = sorted(values)
    pos = q * (len(v) - 1)
    i = int(pos)
    j = min(i + 1, len(v) - 1)
    return float(v[i] + (pos - i) * (v[j] - v[i]))


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def overlaps(a_xy_m: NDArray[np.float64], b_xy_m: NDArray[np.float64]) -> tuple[float, float]:
    """(IoU, containment) of two convex footprints; containment is the intersection over the
    smaller area, high when one is a partial view of the other."""
    inter = polygon_area_m2(convex_intersection(a_xy_m, b_xy_m))
    if inter <= 0.0:
        return 0.0, 0.0
    aa, ab = polygon_area_m2(a_xy_m), polygon_area_m2(b_xy_m)
    return inter / (aa + ab - inter), inter / min(aa, ab)


def consistent(a_xy_m: NDArray[np.float64], b_xy_m: NDArray[np.float64]) -> bool:
    """Two footprints of one object overlap: the intersection covers at least a fifth of the
    smaller one. A view of something else (an occluder's points) is kept out of the hull."""
    return overlaps(a_xy_m, b_xy_m)[1] >= 0.2



@dataclass(frozen=True, eq=False)
class MappedObject:
    """One persistent object of the map (map frame, metres, seconds).

    ``class_probs`` maps every configured class to its probability; ``class_name`` is the most
    likely. ``position_map_m``: fused centroid of the object's points, with isotropic standard
    deviation ``position_std_m``. ``footprint_xy_m``: (M, 2) counter-clockwise polygon.
    ``z_min_m``/``z_max_m``: height range above the floor; ``top_height_m``: the seat/top
    plane's height where one was found. ``view_dir_xy``: the mean unit vector from the cameras
    that saw the object to it (length 1: all views from one side, 0: from all round or unknown).
    """

    object_id: int
    class_name: str
    class_probs: Mapping[str, float]
    existence: float
    position_map_m: tuple[float, float, float]
    position_std_m: float
    footprint_xy_m: NDArray[np.float64]
    z_min_m: float
    z_max_m: float
    top_height_m: float | None
    first_seen_s: float
    last_seen_s: float
    n_observations: int
    confirmed: bool
    view_dir_xy: tuple[float, float] = (0.0, 0.0)

    @property
    def height_m(self) -> float:
        return self.z_max_m

    @property
    def footprint_center_xy_m(self) -> NDArray[np.float64]:
        """Centre of the footprint's bounding box in its own orientation (a rectangle's centre)."""
        return min_perimeter_rectangle(self.footprint_xy_m).mean(axis=0)

    def to_footprint(self, margin_m: float | None = None,
                     min_footprint_m: tuple[float, float] | None = None) -> ObjectFootprint:
        """The costmap's view of this object: its footprint, grown to ``min_footprint_m``
        (the class's least size) on the side its views did not see, when smaller, with
        ``margin_m`` around it (None: its class's, 0.0: none)."""
        polygon = self.footprint_xy_m
        if min_footprint_m is not None:
            polygon = grow_to_least_size(polygon, min_footprint_m, self.view_dir_xy)
        return ObjectFootprint(
            object_id=self.object_id, class_name=self.class_name,
            polygon_xy_m=polygon, z_min_m=self.z_min_m, z_max_m=self.z_max_m,
            existence=self.existence, margin_m=margin_m,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (plain floats and lists)."""
        return {
            "object_id": self.object_id,
            "class_name": self.class_name,
            "class_probs": {k: round(float(v), 6) for k, v in self.class_probs.items()},
            "existence": round(self.existence, 6),
            "position_map_m": [round(float(c), 4) for c in self.position_map_m],
            "position_std_m": round(self.position_std_m, 4),
            "footprint_xy_m": [[round(float(x), 4), round(float(y), 4)] for x, y in self.footprint_xy_m],
            "z_min_m": round(self.z_min_m, 4),
            "z_max_m": round(self.z_max_m, 4),
            "top_height_m": None if self.top_height_m is None else round(self.top_height_m, 4),
            "first_seen_s": self.first_seen_s,
            "last_seen_s": self.last_seen_s,
            "n_observations": self.n_observations,
            "confirmed": self.confirmed,
            "view_dir_xy": [round(float(c), 4) for c in self.view_dir_xy],
        }



@dataclass
class ObjectState:
    """Mutable per-object state inside the object map (fused by :class:`semmap.objects.ObjectMap`)."""

    object_id: int
    class_probs: NDArray[np.float64]  # (K,) in class order
    logodds: float
    position_m: NDArray[np.float64]  # (3,)
    position_var_m2: float
    hull_xy_m: NDArray[np.float64]  # (M, 2)
    first_seen_s: float
    last_seen_s: float
    n_observations: int = 0
    #: Sum of the views' qualities (:func:`semmap.object_evidence.view_quality`): how well
    #: supported the object is, for choosing which of two duplicates to keep.
    support: float = 0.0
    #: Quality of the views the shape comes from: 2 x (within footprint_max_range_m) +
    #: (not cut by the image border); -1 before the first.
    shape_tier: int = -1
    #: Seen at least once within ``footprint_max_range_m``: far views alone do not confirm.
    seen_near: bool = False
    #: When the last miss counted (a frame that should have shown it and did not).
    last_miss_s: float = -math.inf
    #: The camera (position (3,), optical axis (3,), map frame) of the last miss counted.
    last_miss_view: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    z_max_hist: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    z_min_hist: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    top_hist: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    #: Footprint evidence: weighted map-plane cells the views saw the object in.
    evidence: FootprintEvidence = field(default_factory=FootprintEvidence)
    #: The views' footprint edge directions, seen and cut by the field of view: where the
    #: image border cut the views, the rectangle takes the direction of the edges seen.
    edges: EdgeDirections = field(default_factory=EdgeDirections)
    #: Sum of the unit map-plane vectors camera -> object over the views, and their count.
    view_sum_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))
    n_views: int = 0
    footprint_cache: NDArray[np.float64] | None = None
    #: Last snapshot; dropped whenever the state changes (most objects do not, each frame).
    snapshot_cache: MappedObject | None = None

    #: (hull array it was computed from, its bounding box): the hull changes rarely.
    bbox_cache: tuple[NDArray[np.float64], tuple[float, float, float, float]] | None = None

    @property
    def bbox_xy_m(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the hull."""
        if self.bbox_cache is not None and self.bbox_cache[0] is self.hull_xy_m:
            return self.bbox_cache[1]
        lo, hi = self.hull_xy_m.min(axis=0), self.hull_xy_m.max(axis=0)
        box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        self.bbox_cache = (self.hull_xy_m, box)
        return box

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], class_names: Sequence[str], index: int) -> ObjectState:
        """An object of a saved map (one entry of :meth:`ObjectMap.to_dict`'s ``objects``):
        its footprint becomes its evidence, at full weight. ``index``: its place in the dump,
        for errors. Raises :class:`MapError` naming the object and key when it is malformed."""
        try:
            oid = int(d["object_id"])
            probs = np.array([float(d["class_probs"][n]) for n in class_names])
            fp = np.asarray(d["footprint_xy_m"], dtype=np.float64).reshape(-1, 2)
            existence = min(max(float(d["existence"]), 1e-6), 1.0 - 1e-6)
            s = cls(
                object_id=oid, class_probs=probs / probs.sum(), logodds=logit(existence),
                position_m=np.asarray(d["position_map_m"], dtype=np.float64).reshape(3),
                position_var_m2=float(d["position_std_m"]) ** 2, hull_xy_m=fp,
                first_seen_s=float(d["first_seen_s"]), last_seen_s=float(d["last_seen_s"]),
                n_observations=int(d["n_observations"]), shape_tier=0, seen_near=True,
                support=float(d["n_observations"]),
            )
            z0, z1 = float(d["z_min_m"]), float(d["z_max_m"])
            top = d.get("top_height_m")
            view = np.asarray(d.get("view_dir_xy", (0.0, 0.0)), dtype=np.float64).reshape(2)
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"saved object #{index}: missing or bad value ({exc!r})") from exc
        if len(fp) < 3 or probs.sum() <= 0:
            raise MapError(f"saved object {oid}: footprint needs 3+ vertices and some class probability")
        s.z_max_hist.append(z1)
        s.z_min_hist.append(z0)
        s.view_sum_xy, s.n_views = view, 1
        if top is not None:
            s.top_hist.append(float(top))
        # The footprint becomes evidence: its cells, at full weight.
        s.evidence = FootprintEvidence.from_polygon(fp)
        return s

    def absorb(self, drop: ObjectState, shape: bool = True) -> None:
        """Fold another object's state (a duplicate of this one) into this one; without
        ``shape`` (``drop`` was a part of this object, seen in boxes that often named
        something else) its class votes, position, footprint evidence, hull and heights are not taken."""
        keep = self  # the surviving object
        wk, wd = max(keep.support, 1e-6), max(drop.support, 1e-6)
        keep.support += drop.support
        keep.logodds = max(keep.logodds, drop.logodds)
        keep.seen_near = keep.seen_near or drop.seen_near
        keep.snapshot_cache = None
        keep.n_observations += drop.n_observations
        keep.first_seen_s = min(keep.first_seen_s, drop.first_seen_s)
        keep.last_seen_s = max(keep.last_seen_s, drop.last_seen_s)
        if not shape:
            return
        keep.evidence.merge(drop.evidence)
        keep.edges.merge(drop.edges)
        keep.view_sum_xy = keep.view_sum_xy + drop.view_sum_xy
        keep.n_views += drop.n_views
        keep.footprint_cache = None
        # Class evidence fused by weight: multiplying the two posteriors counted the shared
        # views twice and let a few confident boxes of the wrong object outvote many.
        p = (wk * keep.class_probs + wd * drop.class_probs) / (wk + wd)
        p = np.maximum(p, MIN_CLASS_PROB)
        keep.class_probs = p / p.sum()
        va, vb = keep.position_var_m2, drop.position_var_m2
        keep.position_m = (keep.position_m * vb + drop.position_m * va) / (va + vb)
        keep.position_var_m2 = max(va * vb / (va + vb), 1e-4)
        if drop.shape_tier > keep.shape_tier:
            keep.shape_tier = drop.shape_tier
            keep.hull_xy_m = drop.hull_xy_m
            keep.z_max_hist, keep.z_min_hist = drop.z_max_hist, drop.z_min_hist
            keep.top_hist = drop.top_hist
        elif drop.shape_tier == keep.shape_tier:
            keep.hull_xy_m = convex_footprint(np.concatenate([keep.hull_xy_m, drop.hull_xy_m]))
            keep.z_max_hist.extend(drop.z_max_hist)
            keep.z_min_hist.extend(drop.z_min_hist)
            keep.top_hist.extend(drop.top_hist)

    def count_miss(self, stamp_s: float, camera_m: NDArray[np.float64], axis: NDArray[np.float64]) -> float:
        """Record a miss from the camera at ``camera_m`` (3,) looking along ``axis`` (3,, unit,
        map frame); returns how much of a new view it is (0..1): the time since the last
        counted miss over ``MISS_INTERVAL_S``, or the camera's step or turn since then, whichever
        is more."""
        weight = max(0.0, stamp_s - self.last_miss_s) / MISS_INTERVAL_S
        if self.last_miss_view is not None:
            last_m, last_axis = self.last_miss_view
            step_m = float(np.linalg.norm(camera_m - last_m))
            turn_deg = math.degrees(math.acos(min(1.0, max(-1.0, float(axis @ last_axis)))))
            weight = max(weight, step_m / MISS_STEP_M, turn_deg / MISS_TURN_DEG)
        self.last_miss_s = stamp_s
        self.last_miss_view = (camera_m, axis)
        return min(1.0, weight)

    def footprint(self, config: MapConfig) -> NDArray[np.float64]:
        """The footprint from the evidence (:meth:`FootprintEvidence.footprint`), or from the
        observed hull before there is any (cached until the state changes)."""
        if self.footprint_cache is not None:
            return self.footprint_cache
        direction = self.edges.rectangle_direction_rad()
        fp = self.evidence.footprint(config.footprint_evidence_frac, config.footprint_shape, direction)
        if fp is None:
            fp = min_perimeter_rectangle(self.hull_xy_m) if config.footprint_shape == "rectangle" else self.hull_xy_m
        self.footprint_cache = fp
        return fp

    def snapshot(self, class_names: Sequence[str], prior: ClassPrior, config: MapConfig) -> MappedObject:
        """What the map reports of this object (cached until the state changes)."""
        if self.snapshot_cache is not None:
            return self.snapshot_cache
        p = sigmoid(self.logodds)
        footprint = self.footprint(config)
        z_max = quantile(self.z_max_hist, 0.8)
        z_min = quantile(self.z_min_hist, 0.2)
        top = quantile(self.top_hist, 0.5) if self.top_hist else None
        # The votes weighed by the measured geometry (semmap.class_prior); not fused per frame.
        # The top plane, where found, is the height: things stand on tables.
        probs = prior.posterior(self.class_probs, top if top is not None else max(z_max, z_min), footprint)
        k = int(np.argmax(probs))
        n_views = max(self.n_views, 1)
        self.snapshot_cache = MappedObject(
            object_id=self.object_id,
            class_name=class_names[k],
            class_probs={n: float(v) for n, v in zip(class_names, probs, strict=True)},
            existence=p,
            position_map_m=(float(self.position_m[0]), float(self.position_m[1]), float(self.position_m[2])),
            position_std_m=math.sqrt(self.position_var_m2),
            footprint_xy_m=footprint,
            z_min_m=z_min,
            z_max_m=max(z_max, z_min),
            top_height_m=top,
            first_seen_s=self.first_seen_s,
            last_seen_s=self.last_seen_s,
            n_observations=self.n_observations,
            confirmed=p >= config.existence_confirm,
            view_dir_xy=(float(self.view_sum_xy[0]) / n_views, float(self.view_sum_xy[1]) / n_views),
        )
        return self.snapshot_cache
