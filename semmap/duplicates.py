"""Whether two mapped objects are one thing, and whether an observation shows a mapped
object's surface: the pairwise tests :class:`semmap.objects.ObjectMap` associates and merges by.

All footprints here are the evidence footprints (cells several views agree on,
:meth:`semmap.object_state.ObjectState.footprint`), not the hulls of the best views.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from semmap.class_prior import footprint_sides_m, prior_likelihood
from semmap.config import ClassConfig, MapConfig
from semmap.geometry import ObjectObservation
from semmap.object_state import ObjectState, overlaps, quantile
from semmap.polygons import convex_gap_m, convex_intersection, polygon_area_m2

__all__ = ["CONTAINED", "CROSS_CLASS_IOU", "FRAGMENT_TOP_GAP_M", "SAME_TOP_OVERLAP", "DuplicateTests", "MergeKind"]

#: How two objects are one: the same thing mapped twice, or a part of one mapped on its own
#: (whose shape, heights and centroid are a part's, not the object's).
MergeKind = Literal["duplicate", "fragment"]

#: Any-class merge: a new track over an object of another class merges at this IoU.
CROSS_CLASS_IOU = 0.6

#: A same-class footprint mostly inside an object's is a partial view of it.
CONTAINED = 0.6
#: An unassociated observation whose top plane is within this (metres) of a mapped object's
#: top, reaching no higher, and lying mostly inside its footprint shows that object's surface.
SAME_SURFACE_M = 0.04
#: A table's top seen again from elsewhere joins it when the footprints overlap at least this
#: much (intersection over the smaller).
SAME_TOP_OVERLAP = 0.05
#: A fragment: an object from at most this many observations, with ``FRAGMENT_RATIO`` times less
#: support and area than the object it belongs to, lying this much (share of its area) inside a
#: table, or of at most this area (m^2) and within ``FRAGMENT_GAP_M`` of the object (within
#: ``FRAGMENT_TOP_GAP_M`` on the same table top, when both together still fit the class prior).
FRAGMENT_MAX_OBSERVATIONS = 10
FRAGMENT_RATIO = 2.0
FRAGMENT_INSIDE = 0.9
FRAGMENT_AREA_M2 = 0.06
FRAGMENT_GAP_M = 0.10
FRAGMENT_TOP_GAP_M = 0.40


class DuplicateTests:
    """The pairwise tests over the configured ``classes`` (their ``shape`` and ``prior``) and
    the object-map fields of ``config``."""

    def __init__(self, classes: Sequence[ClassConfig], config: MapConfig) -> None:
        self.classes = list(classes)
        self.config = config

    def same_object(self, a: ObjectState, b: ObjectState, seen_now: set[int],
                    fragment_only: bool = False) -> MergeKind | None:
        """Duplicate test: heavy overlap of the footprints whatever the classes, one showing the
        other's surface (:meth:`shows_surface_of`) whatever the classes, or (same class, not two
        detections of one frame) overlap / proximity as for re-association: ``"duplicate"``;
        one a fragment of the other not seen this frame (:meth:`fragment_of`): ``"fragment"``;
        else None. ``fragment_only``: only the fragment test (a pair found only by the wider
        search for fragments).

        Footprints here are the evidence footprints (cells several views agree on), not the
        hulls: one view whose box held a neighbour too grows a hull over that neighbour.
        """
        cfg = self.config
        fa, fb = a.footprint(self.config), b.footprint(self.config)
        reach = float(max(np.ptp(a.hull_xy_m, axis=0).max(), np.ptp(fa, axis=0).max())
                      + max(np.ptp(b.hull_xy_m, axis=0).max(), np.ptp(fb, axis=0).max()))
        dist = float(np.linalg.norm(a.position_m[:2] - b.position_m[:2]))
        if dist > reach:
            return None
        if fragment_only:
            return self._fragment_pair(a, fa, b, fb, seen_now)
        iou, contained = overlaps(fa, fb)
        if iou >= max(CROSS_CLASS_IOU, cfg.reassociate_iou):
            return "duplicate"
        if self.shows_surface_of(a, b) or self.shows_surface_of(b, a):
            return "duplicate"
        same_class = int(np.argmax(a.class_probs)) == int(np.argmax(b.class_probs))
        both_seen_now = a.object_id in seen_now and b.object_id in seen_now
        if same_class and not both_seen_now and (
            iou >= cfg.reassociate_iou or contained >= CONTAINED or dist <= cfg.reassociate_distance_m
            or (contained > SAME_TOP_OVERLAP and self.same_table_top(a, b))
        ):
            return "duplicate"
        return self._fragment_pair(a, fa, b, fb, seen_now)

    def _fragment_pair(self, a: ObjectState, fa: NDArray[np.float64], b: ObjectState, fb: NDArray[np.float64],
                       seen_now: set[int]) -> MergeKind | None:
        """``"fragment"`` when one of the two, not seen this frame, is a part of the other."""
        if (b.object_id not in seen_now and self.fragment_of(b, fb, a, fa)) or (
                a.object_id not in seen_now and self.fragment_of(a, fa, b, fb)):
            return "fragment"
        return None

    def fragment_of(self, small: ObjectState, fp_small: NDArray[np.float64], big: ObjectState,
                     fp_big: NDArray[np.float64]) -> bool:
        """``small`` is a part of ``big`` mapped on its own from a few partial views: few
        observations and far less support than ``big``, of ``big``'s class unless ``big`` is a
        table (whose top boxes of other classes often show), and either lying within a table's
        footprint (a patch of its top, with chair backs above the edge) or a tiny footprint
        touching ``big``'s (the end of a desk)."""
        if small.n_observations > FRAGMENT_MAX_OBSERVATIONS or small.support * FRAGMENT_RATIO > big.support:
            return False
        k = int(np.argmax(big.class_probs))
        table = self.classes[k].shape == "table"
        if k != int(np.argmax(small.class_probs)) and not table:
            return False
        area = polygon_area_m2(fp_small)
        if area <= 0.0:
            return False
        if table and polygon_area_m2(convex_intersection(fp_small, fp_big)) >= FRAGMENT_INSIDE * area:
            return True
        if area > FRAGMENT_AREA_M2 or area * FRAGMENT_RATIO > polygon_area_m2(fp_big):
            return False
        gap = convex_gap_m(fp_small, fp_big)
        if gap <= FRAGMENT_GAP_M:
            return True
        # The far end of a long table seen in a few views of its own: the same top plane, and
        # together no larger than the class allows.
        return gap <= FRAGMENT_TOP_GAP_M and self.same_table_top(small, big) and prior_likelihood(
            self.classes[k].prior, None, footprint_sides_m(np.concatenate([fp_small, fp_big]))) >= 0.5

    def same_table_top(self, a: ObjectState, b: ObjectState) -> bool:
        """Two parts of one table's top: both table-shaped, seen near, the same top plane."""
        k = int(np.argmax(a.class_probs))
        if self.classes[k].shape != "table" or not (a.top_hist and b.top_hist and a.seen_near and b.seen_near):
            return False
        return abs(quantile(a.top_hist, 0.5) - quantile(b.top_hist, 0.5)) <= SAME_SURFACE_M

    def shows_surface_of(self, inner: ObjectState, outer: ObjectState) -> bool:
        """``inner`` is ``outer``'s top mapped a second time (often under another class): both
        seen near, the same top plane (within ``SAME_SURFACE_M``), ``inner`` reaching no
        higher and lying mostly inside ``outer``'s footprint (see :meth:`share_on_surface`).

        The object-level form of :meth:`semmap.objects.ObjectMap._surface_owner`, for a phantom whose first views had no
        top plane or came before ``outer`` had one, so that test could not stop it at birth.
        """
        if not (inner.seen_near and inner.top_hist and inner.z_max_hist):
            return False
        # Only a table's top is a surface a whole object shows again: chairs side by side share
        # a seat height, and one whose footprint grew over its neighbour is still two chairs.
        if self.classes[int(np.argmax(outer.class_probs))].shape != "table":
            return False
        return self.share_on_surface(quantile(inner.top_hist, 0.5), quantile(inner.z_max_hist, 0.8),
                                      inner.footprint(self.config), outer) >= CONTAINED

    def share_on_surface(self, top_m: float, z_max_m: float, fp_xy_m: NDArray[np.float64], outer: ObjectState) -> float:
        """The share of ``fp_xy_m`` inside ``outer``'s footprint when something with this top
        plane and reach shows ``outer``'s surface (``outer`` seen near, the same top within
        ``SAME_SURFACE_M``, reaching no higher), else 0: the test of :meth:`semmap.objects.ObjectMap._surface_owner`
        (one observation) and :meth:`shows_surface_of` (a mapped object)."""
        if not outer.seen_near or not outer.top_hist or not outer.z_max_hist:
            return 0.0
        if abs(top_m - quantile(outer.top_hist, 0.5)) > SAME_SURFACE_M:
            return 0.0
        if z_max_m > quantile(outer.z_max_hist, 0.8) + SAME_SURFACE_M:
            return 0.0
        area = polygon_area_m2(fp_xy_m)
        if area <= 0.0:
            return 0.0
        return polygon_area_m2(convex_intersection(outer.footprint(self.config), fp_xy_m)) / area

    def same_top(self, s: ObjectState, o: ObjectObservation) -> bool:
        """The observation shows more of a table-shaped object's top: its top plane is the
        object's (within ``SAME_SURFACE_M``) and it reaches no higher. Another part of a long
        table seen from its other end overlaps the part seen before only at the seam."""
        k = int(np.argmax(s.class_probs))
        if self.classes[k].shape != "table" or o.top_height_m is None or not s.top_hist:
            return False
        top = quantile(s.top_hist, 0.5)
        return abs(o.top_height_m - top) <= SAME_SURFACE_M and o.z_max_m <= top + SAME_SURFACE_M
