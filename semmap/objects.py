"""The object map: persistent objects fused from per-frame observations.

Each frame's :class:`~semmap.geometry.ObjectObservation` list is associated to known objects:
first by track id (the tracker already did the frame-to-frame work), then, for a new track id,
by class and footprint overlap or centroid distance, so the same table seen again after its
track was lost is the same object. Unmatched observations start new objects.

Every object fuses:

* class probabilities: a Bayesian update per observation with the detector's score as the
  likelihood of the reported class and the rest spread evenly over the other classes;
* existence (log-odds): raised by each observation as much as the view is good
  (:func:`~semmap.object_evidence.view_quality`; up to just below confirmation while the
  object was only seen beyond ``footprint_max_range_m``); lowered by the class's
  ``miss_decay`` for each view that should have shown the object (its centroid projects into
  the image, in range, not occluded by nearer depth) but no observation matched it, frames
  from one place at video rate counting once
  (:meth:`~semmap.object_state.ObjectState.count_miss`); clamped below
  ``existence_max`` so that even a long-seen object fades once it is gone;
* position: inverse-variance fusion of observed centroids (noise grows with range);
* footprint: weighted 2 cm cells where views saw the object's points (views from different
  sides complete each other; :mod:`semmap.object_evidence`), reported as the hull of the
  well-supported cells or their least-perimeter rectangle;
* height range: robust quantiles over recent observations (partial views cut the top).

Objects below ``existence_remove_below`` are removed, and unconfirmed ones not seen again
within ``tentative_timeout_s``, so false positives fade away. Each object's state and its
reported snapshot are in :mod:`semmap.object_state`, the pairwise tests of one thing mapped
twice in :mod:`semmap.duplicates`; this module associates and merges.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semmap.camera_view import CameraView
from semmap.class_extent import MEASURED_ONLY_MARGIN_M, contradicts_class
from semmap.class_prior import ClassPrior, footprint_sides_m, oversize_likelihood, top_fits
from semmap.config import ClassConfig, MapConfig
from semmap.costmap import ObjectFootprint
from semmap.duplicates import (
    CONTAINED,
    CROSS_CLASS_IOU,
    FRAGMENT_TOP_GAP_M,
    SAME_TOP_OVERLAP,
    DuplicateTests,
)
from semmap.errors import MapError
from semmap.geometry import ObjectObservation
from semmap.object_evidence import view_quality
from semmap.object_state import (
    MIN_CLASS_PROB,
    MappedObject,
    ObjectState,
    consistent,
    logit,
    overlaps,
    sigmoid,
)
from semmap.polygons import (
    convex_footprint,
    polygon_area_m2,
    simplify_polygon,
)

log = logging.getLogger(__name__)

__all__ = ["CameraView", "MappedObject", "ObjectMap"]

#: Views beyond ``footprint_max_range_m`` alone keep an object this far (log-odds) below
#: confirmation.
_UNCONFIRMED_MARGIN = 0.01
#: Weight of a view farther than ``footprint_max_range_m`` (noisier depth).
_FAR_WEIGHT = 0.3


#: Position variance factor of views cut by the image border.
_EDGE_VARIANCE_FACTOR = 9.0
class ObjectMap:
    """Persistent objects from per-frame observations (see the module doc).

    ``classes``: the configured classes (their order is the class-probability order, their
    ``miss_decay`` the per-class existence decay, their ``prior`` the geometric class prior).
    ``config``: the object-map fields of :class:`~semmap.config.MapConfig`. ``vote_groups``:
    reported class -> the classes a detection of it votes for (the detector cannot tell them
    apart; the geometric prior does).
    """

    def __init__(self, classes: Sequence[ClassConfig], config: MapConfig | None = None,
                 vote_groups: Mapping[str, Sequence[str]] | None = None) -> None:
        if not classes:
            raise MapError("the object map needs at least one class")
        self.config = config if config is not None else MapConfig()
        self.classes = list(classes)
        self.class_names = [c.name for c in self.classes]
        self._class_index = {n: i for i, n in enumerate(self.class_names)}
        self._prior = ClassPrior(self.classes)
        self._pairs = DuplicateTests(self.classes, self.config)
        #: Reported class -> class indices its detections vote for (a detector's class that
        #: stands for several of ours, see semmap.detection.builtin.vote_groups).
        self._votes_for = {k: [self._class_index[c] for c in v if c in self._class_index]
                           for k, v in (vote_groups or {}).items()}
        self._objects: dict[int, ObjectState] = {}
        self._track_to_object: dict[int, int] = {}
        self._next_id = 1

    # --- queries --------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._objects)

    def objects(self, confirmed_only: bool = False) -> list[MappedObject]:
        """Snapshot of the objects, by id."""
        out = [s.snapshot(self.class_names, self._prior, self.config) for _, s in sorted(self._objects.items())]
        return [o for o in out if o.confirmed] if confirmed_only else out

    def footprints(self, confirmed_only: bool = True) -> list[ObjectFootprint]:
        """Objects as costmap footprints, each with its class's margin and grown to its class's
        least footprint (:meth:`MappedObject.to_footprint`), unless it stands taller than its
        class allows (:func:`semmap.class_extent.contradicts_class`)."""
        by_name = {c.name: c for c in self.classes}
        out = []
        for o in self.objects(confirmed_only):
            cls = by_name[o.class_name]
            if contradicts_class(cls, o.z_max_m):
                # Its measured footprint blocks, with no class's margin or size.
                out.append(o.to_footprint(MEASURED_ONLY_MARGIN_M, None))
            else:
                out.append(o.to_footprint(cls.margin_m, cls.min_footprint_m))
        return out

    def class_probabilities(self) -> dict[int, NDArray[np.float32]]:
        """Object id -> (K,) class probabilities in ``class_names`` order (for the class layer)."""
        return {oid: np.fromiter(s.snapshot(self.class_names, self._prior, self.config).class_probs.values(), np.float32, len(self.class_names))
                for oid, s in self._objects.items()}

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dump of every object."""
        return {"classes": self.class_names, "objects": [o.to_dict() for o in self.objects()]}

    def load_dict(self, data: Mapping[str, Any]) -> None:
        """Replace the objects by those of a :meth:`to_dict` dump (a saved map).

        Each object comes back with its id, class probabilities, existence, position and
        uncertainty, footprint (as its evidence), height range and times; track links are
        not kept (tracks do not survive a restart). Raises :class:`MapError` naming the
        object and key when the dump does not fit this map's classes or is malformed.
        """
        if list(data.get("classes", [])) != self.class_names:
            raise MapError(f"saved object map has classes {data.get('classes')}, this map {self.class_names}")
        objects: dict[int, ObjectState] = {}
        for i, d in enumerate(data.get("objects", [])):
            s = ObjectState.from_dict(d, self.class_names, i)
            objects[s.object_id] = s
        self._objects = objects
        self._track_to_object = {}
        self._next_id = max(objects, default=0) + 1

    # --- update ---------------------------------------------------------------------------

    def update(
        self,
        observations: Iterable[ObjectObservation],
        stamp_s: float,
        view: CameraView | None = None,
    ) -> list[int]:
        """Fuse one frame's observations; returns the object id of each observation in order.

        ``view`` (the frame's depth and pose) enables negative evidence for objects that were
        expected in the image but not observed; without it existence is only ever raised and
        tentative objects time out. Observations of unknown classes raise :class:`MapError`.
        """
        obs = list(observations)
        for o in obs:
            if o.class_name not in self._class_index:
                raise MapError(
                    f"observation of track {o.track_id} has class {o.class_name!r}; "
                    f"known classes: {self.class_names}"
                )
        used: set[int] = set()
        shown: set[int] = set()  # objects whose surface another track's box showed
        assigned: dict[int, int] = {}
        order = sorted(range(len(obs)), key=lambda i: -obs[i].score)
        for i in order:
            oid = self._associate(obs[i], used)
            if oid is None:
                owner = self._surface_owner(obs[i])
                if owner is not None:
                    # No new object, and its geometry is not fused (its track belongs to
                    # something else); a second box of the same class is still a detection.
                    if int(np.argmax(self._objects[owner].class_probs)) in self._vote_indices(obs[i].class_name):
                        self._raise_existence(self._objects[owner], obs[i])
                    assigned[i] = owner
                    shown.add(owner)
                    continue
                oid = self._create(obs[i], view)
            else:
                self._fuse(self._objects[oid], obs[i], view)
            used.add(oid)
            assigned[i] = oid
            self._track_to_object[obs[i].track_id] = oid
        merged = self._merge_duplicates(used, used)
        self._negative_evidence(used | shown, view, stamp_s)
        self._prune(stamp_s)
        return [merged.get(assigned[i], assigned[i]) for i in range(len(obs))]

    def _nearby(
        self, lo_xy: NDArray[np.float64], hi_xy: NDArray[np.float64], xy: NDArray[np.float64]
    ) -> list[int]:
        """Ids of objects whose footprint's bounding box meets [lo, hi] or whose centroid is
        within ``reassociate_distance_m`` of ``xy``: the only ones worth an overlap test."""
        if not self._objects:
            return []
        ids = list(self._objects)
        boxes = np.array([self._objects[i].bbox_xy_m for i in ids])  # (N, 4)
        pos = np.array([self._objects[i].position_m[:2] for i in ids])  # (N, 2)
        overlap = (boxes[:, 0] <= hi_xy[0]) & (boxes[:, 2] >= lo_xy[0]) & (
            boxes[:, 1] <= hi_xy[1]) & (boxes[:, 3] >= lo_xy[1])
        close = np.linalg.norm(pos - xy, axis=1) <= self.config.reassociate_distance_m
        return [ids[i] for i in np.nonzero(overlap | close)[0]]

    def _merge_duplicates(self, touched: set[int], seen_now: set[int]) -> dict[int, int]:
        """Merge objects updated this frame into older duplicates (the same thing detected
        under two classes, or a track that started before re-association could catch it).
        Returns removed id -> surviving id."""
        merged: dict[int, int] = {}
        for oid in sorted(touched):
            if oid not in self._objects:
                continue
            me = self._objects[oid]
            lo, hi = me.hull_xy_m.min(axis=0), me.hull_xy_m.max(axis=0)
            near = set(self._nearby(lo, hi, me.position_m[:2]))
            # Fragments are looked for farther: as far as one may lie from its object.
            wide = self._nearby(lo - FRAGMENT_TOP_GAP_M, hi + FRAGMENT_TOP_GAP_M, me.position_m[:2])
            for other in sorted(wide):
                if other == oid or other not in self._objects or oid not in self._objects:
                    continue
                a, b = self._objects[other], self._objects[oid]
                kind = self._pairs.same_object(a, b, seen_now, fragment_only=other not in near)
                if kind is not None:
                    # The better-supported object survives, whatever the ids (ties: the older).
                    keep, drop = (a, b) if (a.support, -a.object_id) >= (b.support, -b.object_id) else (b, a)
                    self._absorb(keep, drop, shape=kind == "duplicate")
                    merged[drop.object_id] = keep.object_id
                    break
        # Chains (a -> b -> c) resolve to the final survivor.
        for k in list(merged):
            while merged[k] in merged:
                merged[k] = merged[merged[k]]
        return merged

    def _absorb(self, keep: ObjectState, drop: ObjectState, shape: bool = True) -> None:
        """Fold ``drop`` into ``keep`` and remove it (``shape``: :meth:`ObjectState.absorb`)."""
        keep.absorb(drop, shape)
        for tid, o in self._track_to_object.items():
            if o == drop.object_id:
                self._track_to_object[tid] = keep.object_id
        del self._objects[drop.object_id]
        log.debug("object %d merged into %d (%s)", drop.object_id, keep.object_id, "duplicate" if shape else "fragment")

    def _associate(self, o: ObjectObservation, used: set[int]) -> int | None:
        cfg = self.config
        oid = self._track_to_object.get(o.track_id)
        fp = np.asarray(o.footprint_xy_m, dtype=np.float64)
        track_object: int | None = None
        if oid is not None and oid in self._objects and oid not in used:
            s = self._objects[oid]
            if np.linalg.norm(s.position_m[:2] - o.centroid_xy_m) <= cfg.track_gate_m:
                if consistent(s.hull_xy_m, fp):
                    return oid
                # The track's box moved off its object (a camera passing along a long desk
                # whose first view was a corner): an object this view overlaps takes it.
                track_object = oid
            else:
                log.debug("track %d jumped %.2f m from object %d: new object", o.track_id,
                          float(np.linalg.norm(s.position_m[:2] - o.centroid_xy_m)), oid)
        ks = self._votes_for.get(o.class_name) or [self._class_index[o.class_name]]
        best: tuple[float, float, int] | None = None
        for cand in self._nearby(fp.min(axis=0), fp.max(axis=0), o.centroid_xy_m):
            if cand in used or cand == track_object:
                continue
            s = self._objects[cand]
            iou, contained = overlaps(s.footprint(self.config), fp)
            dist = float(np.linalg.norm(s.position_m[:2] - o.centroid_xy_m))
            same_class = int(np.argmax(s.class_probs)) in ks
            ok = (same_class and (iou >= cfg.reassociate_iou or contained >= CONTAINED
                                  or dist <= cfg.reassociate_distance_m
                                  or (contained > SAME_TOP_OVERLAP and self._pairs.same_top(s, o)))) or (
                iou >= max(CROSS_CLASS_IOU, cfg.reassociate_iou)
            )
            score = max(iou, contained if same_class else 0.0)
            if ok and (best is None or (score, -dist) > (best[0], best[1])) and (track_object is None or score > 0):
                best = (score, -dist, cand)
        if best is None:
            return track_object
        return best[2]

    def _surface_owner(self, o: ObjectObservation) -> int | None:
        """The object whose surface an unassociated observation shows, or None.

        A detector box of an object half-hidden behind another (a chair behind a coffee
        table) often holds mostly the nearer object's points, and a detector may name one
        object twice under two classes in one frame: such an observation's top plane is the
        mapped object's top, it reaches no higher, and it lies inside the object's footprint.
        It would become a phantom (a second, thinner object over the first, or the
        nearer object again where the hidden one's track had been) that narrows passages.
        A real object inside another's footprint (a chair tucked under a desk) has a top of
        its own (its seat) and reaches higher (its backrest).
        """
        if o.top_height_m is None:
            return None
        fp = np.asarray(o.footprint_xy_m, dtype=np.float64)
        if polygon_area_m2(fp) <= 0.0:
            return None
        best: tuple[float, int] | None = None
        for cand in self._nearby(fp.min(axis=0), fp.max(axis=0), o.centroid_xy_m):
            inside = self._pairs.share_on_surface(o.top_height_m, o.z_max_m, fp, self._objects[cand])
            if inside >= CONTAINED and (best is None or inside > best[0]):
                best = (inside, cand)
        if best is not None:
            log.debug("track %d (%s) shows the surface of object %d: not a new object", o.track_id,
                      o.class_name, best[1])
        return None if best is None else best[1]

    def _class_likelihood(self, class_name: str, score: float) -> NDArray[np.float64]:
        k = len(self.class_names)
        if k == 1:
            return np.ones(1)
        # A detection below chance would count *against* its own class; floor it at chance.
        s = min(max(float(score), 1.0 / k + 1e-3), 0.999)
        lik = np.full(k, (1.0 - s) / (k - 1))
        lik[self._votes_for.get(class_name) or self._class_index[class_name]] = s
        return lik

    def _sigma2(self, o: ObjectObservation) -> float:
        sigma = self.config.position_sigma_m + self.config.position_sigma_per_m * o.range_m
        return sigma * sigma

    def _create(self, o: ObjectObservation, view: CameraView | None = None) -> int:
        oid = self._next_id
        self._next_id += 1
        prior = np.full(len(self.class_names), 1.0 / len(self.class_names))
        s = ObjectState(
            object_id=oid, class_probs=prior, logodds=logit(self.config.existence_initial),
            position_m=np.asarray(o.centroid_map_m, dtype=np.float64),
            position_var_m2=self._sigma2(o), hull_xy_m=np.asarray(o.footprint_xy_m, np.float64),
            first_seen_s=o.stamp_s, last_seen_s=o.stamp_s,
        )
        self._objects[s.object_id] = s
        self._fuse(s, o, view, first=True)
        log.debug("new object %d (%s) at %s", oid, o.class_name, np.round(o.centroid_map_m, 2))
        return oid

    def _fuse(self, s: ObjectState, o: ObjectObservation, view: CameraView | None = None,
              first: bool = False) -> None:
        cfg = self.config
        s.snapshot_cache = None
        p = s.class_probs * self._class_likelihood(o.class_name, o.score)
        p = np.maximum(p / p.sum(), MIN_CLASS_PROB)
        s.class_probs = p / p.sum()
        self._raise_existence(s, o)
        s.n_observations += 1
        s.last_seen_s = max(s.last_seen_s, o.stamp_s)
        s.first_seen_s = min(s.first_seen_s, o.stamp_s)
        fp = np.asarray(o.footprint_xy_m, dtype=np.float64)
        if not first and not self._top_fits(o.class_name, o.top_height_m):
            # The box's cluster held another object's top (a chair's seat under the table):
            # the detection says the table is there, the outline is the chair's. Its top is
            # kept only by an object without a top of its own: a track whose every view shows
            # another object's surface is that object's duplicate, and the top shows it.
            log.debug("object %d: top of track %d at %.2f m is not a %s top, outline ignored",
                      s.object_id, o.track_id, o.top_height_m, o.class_name)
            if o.top_height_m is not None and not any(self._top_fits(o.class_name, t) for t in s.top_hist):
                s.top_hist.append(o.top_height_m)
            return
        if not first and not consistent(s.hull_xy_m, fp):
            # The track's box showed something else this time (an occluder in front): it
            # still says the object is there, but not where or how big.
            log.debug("object %d: observation of track %d off its footprint, geometry ignored",
                      s.object_id, o.track_id)
            return
        if not first:
            r2 = self._sigma2(o)
            if o.at_image_edge:
                r2 *= _EDGE_VARIANCE_FACTOR  # a cut view's centroid is biased towards the image
            x = np.asarray(o.centroid_map_m, dtype=np.float64)
            w = s.position_var_m2 / (s.position_var_m2 + r2)
            s.position_m = s.position_m + w * (x - s.position_m)
            # Floor on the variance: the estimate keeps following a slowly drifting pose.
            s.position_var_m2 = max(s.position_var_m2 * r2 / (s.position_var_m2 + r2), 1e-4)
        # Shape and height come from the best class of views seen so far: near ones before
        # far ones, then whole ones before ones cut by the image border. A better view resets
        # what worse ones said. Near first: beyond footprint_max_range_m depth noise (growing
        # with range squared) joins neighbours into one blob, and a hull from such a view made
        # near views of the neighbour associate to this object; a cut near view is partial
        # but where it sees the object it is right.
        tier = int(not o.at_image_edge) + 2 * int(o.range_m <= cfg.footprint_max_range_m)
        if tier > s.shape_tier:
            s.shape_tier = tier
            s.hull_xy_m = fp
            s.z_max_hist.clear()
            s.z_min_hist.clear()
            s.top_hist.clear()
        elif tier == s.shape_tier:
            s.hull_xy_m = simplify_polygon(convex_footprint(np.concatenate([s.hull_xy_m, fp])), 0.01)
        if tier == s.shape_tier:
            s.z_max_hist.append(o.z_max_m)
            s.z_min_hist.append(o.z_min_m)
            if o.top_height_m is not None:
                s.top_hist.append(o.top_height_m)
        # Every view adds evidence where it saw the object (partial views are incomplete,
        # not wrong); each cell counts once per view.
        # The points' heights tell which cells the view could have seen (a seat under a table).
        pts = o.voxels_map_m if len(o.voxels_map_m) else o.points_xy_m if len(o.points_xy_m) else fp
        near = o.range_m <= cfg.footprint_max_range_m
        s.evidence.add_view(pts, 1.0 if near else _FAR_WEIGHT, view)
        if o.footprint_edge_cut is not None:
            s.edges.add_view(fp, o.footprint_edge_cut)
        if o.camera_xy_m is not None:
            d = o.centroid_xy_m - np.asarray(o.camera_xy_m, dtype=np.float64)
            n = float(np.hypot(d[0], d[1]))
            if n > 1e-6:
                s.view_sum_xy = s.view_sum_xy + d / n
                s.n_views += 1
        s.footprint_cache = None

    def _vote_indices(self, class_name: str) -> list[int]:
        return self._votes_for.get(class_name) or [self._class_index[class_name]]

    def _raise_existence(self, s: ObjectState, o: ObjectObservation) -> None:
        """Existence rises with the quality of the view: one close, clean view can confirm."""
        cfg = self.config
        s.snapshot_cache = None
        # Beyond footprint_max_range_m depth noise blurs an object into what stands behind it
        # (a half-hidden whiteboard's box then shows the wall): such views raise existence,
        # but only a nearer one confirms the object (else it stays tentative and times out).
        s.seen_near = s.seen_near or o.range_m <= cfg.footprint_max_range_m
        cap = logit(cfg.existence_max) if s.seen_near else logit(cfg.existence_confirm) - _UNCONFIRMED_MARGIN
        cls = self.classes[self._class_index[o.class_name]]
        # A detector's class that stands for several of ours (COCO's one table) fits any of them.
        height, sides = o.top_height_m if o.top_height_m is not None else o.z_max_m, footprint_sides_m(o.footprint_xy_m)
        fit = max(oversize_likelihood(self.classes[k].prior, height, sides) for k in self._vote_indices(o.class_name))
        has_top = (o.top_height_m is not None and self._top_fits(o.class_name, o.top_height_m)) if cls.hollow != "none" else None
        q = view_quality(o.score, o.range_m, o.at_image_edge, o.n_voxels, has_top, cfg.footprint_max_range_m, fit)
        s.support += q
        s.logodds = min(s.logodds + cfg.existence_hit_logodds * q, max(s.logodds, cap))

    def _top_fits(self, class_name: str, top_height_m: float | None) -> bool:
        """A top plane at ``top_height_m`` can be the top of an object the detector class
        ``class_name`` stands for (:func:`semmap.class_prior.top_fits`); True without a top
        and for classes not shaped as tables."""
        if top_height_m is None or self.classes[self._class_index[class_name]].shape != "table":
            return True
        return any(top_fits(self.classes[k].prior, top_height_m) for k in self._vote_indices(class_name))

    def _negative_evidence(self, matched: set[int], view: CameraView | None, stamp_s: float) -> None:
        if view is None:
            return
        ids = [oid for oid in self._objects if oid not in matched]
        if not ids:
            return
        cents = np.array([self._objects[oid].position_m for oid in ids])
        # A miss counts only where the detector should have seen the object: in view, not
        # occluded (expects_visible), and near enough to be detected.
        T = np.asarray(view.T_map_camera, dtype=np.float64)
        cam, axis = T[:3, 3], T[:3, 2]
        near = np.linalg.norm(cents - cam, axis=1) <= self.config.footprint_max_range_m
        visible = view.expects_visible(cents) & near
        for oid, vis in zip(ids, visible, strict=True):
            if vis:
                s = self._objects[oid]
                decay = self.classes[int(np.argmax(s.class_probs))].miss_decay
                s.logodds -= decay * s.count_miss(stamp_s, cam, axis)
                s.snapshot_cache = None

    def _prune(self, stamp_s: float) -> None:
        cfg = self.config
        for oid in list(self._objects):
            s = self._objects[oid]
            p = sigmoid(s.logodds)
            stale = p < cfg.existence_confirm and stamp_s - s.last_seen_s > cfg.tentative_timeout_s
            if p < cfg.existence_remove_below or stale:
                log.debug("object %d removed (existence %.2f)", oid, p)
                del self._objects[oid]
        for tid in [t for t, oid in self._track_to_object.items() if oid not in self._objects]:
            del self._track_to_object[tid]
