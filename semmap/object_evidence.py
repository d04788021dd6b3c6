"""Footprint evidence of one mapped object: the map-plane cells its views saw it in.

Each object keeps 2 cm cells (:data:`CELL_M`) with a weight: every view adds its weight once to
each cell holding one of the object's points. The footprint is made of the cells holding at
least a fraction of the well-seen cells' weight (the 90th percentile), so stray noise cells do
not grow it, or seen in most of the views that could have seen them (below), reported as
their convex hull or as an oriented rectangle around them. Kept cells lying apart (groups
linked within ``GROUP_LINK_M``) count only when one of them is as well seen as the object's
well-seen cells or they hold a share of its weight: views from afar hit each cell of an object
only a few times, so background points that recur in two or three views (the wall behind a
low table, joined to it by flying pixels) reach the kept weight, and two such cells a metre off
would stretch the rectangle, and move its centre, half a metre off the object. A table's legs,
apart from each other under a top seen edge-on, are seen by every view.

The rectangle is the bounding rectangle of least *perimeter*, not of least area. The kept
cells are often an L or a triangle rather than a full rectangle: a chair's backrest is seen by
every view while its seat is hidden behind it from most, so the backrest and one side of the
seat outweigh the rest. For a right triangle the least-area rectangle is ambiguous (aligned
with a leg or with the hypotenuse, both enclose the same area) and often comes out turned by
about 45 degrees, its centre 15-20 cm off; the least-perimeter rectangle is aligned with the
legs, the object's own sides. For a filled rectangle both agree.

Weight alone penalises a part for the views that could not see it. A chair pushed in under a
table's edge has its seat hidden by the table top from most of the views that see its backrest
(13 views against 33), so the seat fell below the fraction and the chair mapped as a strip
along its backrest. Each cell therefore also keeps the weight of the views that could have seen
the object there (the cell projects into the image, within range, and the measured depth at its
top, the highest point seen in it, is not nearer: :meth:`CameraView.expects_visible`), and a
cell seen in ``HIT_RATIO`` of those is kept too. Noise cells round an object are in plain view
in most views that miss them; the seat is hidden in those. A cell's visible weight counts only
from its first hit on, so a cell must also be visible in ``MIN_VISIBLE_FRAC`` of all the
object's views: a neighbour's points that one late view joined to the object would otherwise
have a ratio of one, and grew two chairs side by side into one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from semmap.camera_view import CameraView
from semmap.clustering import euclidean_clusters
from semmap.polygons import (
    convex_footprint,
    inside_convex,
    min_perimeter_rectangle,
    rectangle_along,
)

__all__ = ["CELL_M", "FootprintEvidence", "cell_centres", "cell_keys", "view_quality"]

#: A detector score at or above this is full evidence of the box (COCO models top out near it).
QUALITY_FULL_SCORE = 0.6
#: Views within this range are full evidence; beyond, the weight falls linearly to
#: ``QUALITY_FAR_WEIGHT`` at ``far_range_m`` (depth noise grows with range squared).
QUALITY_NEAR_RANGE_M = 3.5
QUALITY_FAR_WEIGHT = 0.25
#: Weight of a view cut by the image border (part of the object is missing).
QUALITY_EDGE_WEIGHT = 0.6
#: Voxels of a fully measured object; fewer is a glimpse (weight in proportion).
QUALITY_FULL_VOXELS = 60
#: Weight of a view of a hollow-bottom object where no top plane was found (the 3D fit
#: does not agree with the class).
QUALITY_NO_TOP_WEIGHT = 0.7

#: Kept cells this close (metres) are one group: the parts of one piece of furniture seen apart
#: (a chair's backrest and front legs, its seat hidden between them) are never farther apart.
GROUP_LINK_M = 0.4
#: A group apart is also part of the object when it holds this share of the heaviest group's
#: weight (a part every view sees a little of).
GROUP_MIN_SHARE = 0.025
#: Cells are grouped on this coarser grid (metres; a quarter of the link, so the link holds
#: within a cell's diagonal).
GROUP_CELL_M = 0.1

#: A cell is also kept when seen in this share of the views that could have seen it ...
HIT_RATIO = 0.7
#: ... when those weigh at least this share of all the object's views and at least
#: ``MIN_VISIBLE_WEIGHT`` (about that many clean views): module doc.
MIN_VISIBLE_FRAC = 0.3
MIN_VISIBLE_WEIGHT = 5.0
#: A cell's top is hidden when the measured depth there is nearer by more than this (metres):
#: tighter than the existence misses' tolerance, as a chair's backrest hides its seat only a
#: few tens of centimetres behind it.
VISIBILITY_TOLERANCE_M = 0.1

#: Cell size of the evidence, metres.
CELL_M = 0.02
_KEY_SHIFT = np.int64(1 << 31)


def cell_keys(xy_m: NDArray[np.float64], cell_m: float = CELL_M) -> NDArray[np.int64]:
    """(N,) integer keys of the cells (side ``cell_m``) holding map-plane points (N, 2)."""
    ij = np.floor(xy_m / cell_m).astype(np.int64) + _KEY_SHIFT // 2
    return ij[:, 0] * _KEY_SHIFT + ij[:, 1]


def cell_centres(keys: NDArray[np.int64], cell_m: float = CELL_M) -> NDArray[np.float64]:
    """(N, 2) map-plane centres of the cells (side ``cell_m``) with keys (N,)."""
    i = keys // _KEY_SHIFT - _KEY_SHIFT // 2
    j = keys % _KEY_SHIFT - _KEY_SHIFT // 2
    return (np.stack([i, j], axis=1).astype(np.float64) + 0.5) * cell_m


@dataclass
class FootprintEvidence:
    """Weighted cells of one object (see the module doc): ``keys`` (C,) sorted, ``weights`` (C,)
    the views that saw the object there, ``visible`` (C,) the views that could have (each
    view's weight), ``top_z_m`` (C,) the highest of the object's points seen there (map frame;
    NaN unknown)."""

    keys: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    weights: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    visible: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    top_z_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    #: Sum of the views' weights.
    total_weight: float = 0.0

    def __len__(self) -> int:
        return len(self.keys)

    @classmethod
    def from_polygon(cls, polygon_xy_m: NDArray[np.float64]) -> FootprintEvidence:
        """Evidence of a known convex footprint (M, 2) (a restored map): its cells, weight 1."""
        lo, hi = polygon_xy_m.min(axis=0), polygon_xy_m.max(axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + CELL_M, CELL_M), np.arange(lo[1], hi[1] + CELL_M, CELL_M))
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        inside = inside_convex(polygon_xy_m, grid)
        ev = cls()
        ev.add_view(grid[inside] if inside.any() else polygon_xy_m, 1.0)
        return ev

    def add_view(self, points_m: NDArray[np.float64], weight: float, view: CameraView | None = None) -> None:
        """Add one view: ``weight`` once to each cell holding one of its points (N, 2) on the
        map plane or (N, 3) in the map frame, and to the visible weight of each cell the view
        could have seen the object in (``view.expects_visible`` at the cell's top, within
        ``VISIBILITY_TOLERANCE_M``). Without a view, or without a cell's height, every cell
        counts as visible: the hit ratio is then the share of the views that saw it."""
        pts = np.asarray(points_m, dtype=np.float64)
        keys, inv = np.unique(cell_keys(pts[:, :2]), return_inverse=True)
        top = np.full(len(keys), np.nan)
        if pts.shape[1] == 3:
            np.fmax.at(top, inv.reshape(-1), pts[:, 2])
        pos = np.searchsorted(self.keys, keys)  # (K,) a merge, not a re-sort of everything
        known = pos < len(self.keys)
        known[known] = self.keys[pos[known]] == keys[known]
        fresh = ~known
        w, vis, z = self.weights.copy(), self.visible.copy(), self.top_z_m.copy()
        w[pos[known]] += weight
        z[pos[known]] = np.fmax(z[pos[known]], top[known])
        self.keys = np.insert(self.keys, pos[fresh], keys[fresh])
        self.weights = np.insert(w, pos[fresh], weight)
        self.visible = np.insert(vis, pos[fresh], 0.0)
        self.top_z_m = np.insert(z, pos[fresh], top[fresh])
        seeable = np.ones(len(self.keys), dtype=bool)
        if view is not None:
            # Cells this view hit were visible; only the others are projected and tested.
            hit = np.zeros(len(self.keys), dtype=bool)
            hit[np.searchsorted(self.keys, keys)] = True
            tested = ~hit & ~np.isnan(self.top_z_m)
            seeable[tested] = view.expects_visible(
                np.column_stack([cell_centres(self.keys[tested]), self.top_z_m[tested]]), VISIBILITY_TOLERANCE_M)
        self.visible[seeable] += weight
        self.total_weight += weight

    def merge(self, other: FootprintEvidence) -> None:
        """Fold another object's evidence into this one (two objects found to be one)."""
        keys, inv = np.unique(np.concatenate([self.keys, other.keys]), return_inverse=True)
        inv = inv.reshape(-1)
        n = len(keys)
        self.weights = np.bincount(inv, weights=np.concatenate([self.weights, other.weights]),
                                   minlength=n).astype(np.float64)
        self.visible = np.bincount(inv, weights=np.concatenate([self.visible, other.visible]),
                                   minlength=n).astype(np.float64)
        top = np.full(n, np.nan)
        np.fmax.at(top, inv, np.concatenate([self.top_z_m, other.top_z_m]))
        self.keys, self.top_z_m = keys, top
        self.total_weight += other.total_weight

    def kept(self, frac: float) -> tuple[NDArray[np.bool_], float]:
        """(C,) the cells the footprint is made of, and the 90th-percentile cell weight: those
        holding ``frac`` of that weight, or seen in ``HIT_RATIO`` of the views that could have
        seen them when those are enough (``MIN_VISIBLE_FRAC``, ``MIN_VISIBLE_WEIGHT``)."""
        k90 = int(0.9 * (len(self.weights) - 1))
        p90 = float(np.partition(self.weights, k90)[k90])
        min_visible = max(MIN_VISIBLE_WEIGHT, MIN_VISIBLE_FRAC * self.total_weight)
        return (self.weights >= frac * p90) | ((self.weights >= HIT_RATIO * self.visible)
                                               & (self.visible >= min_visible)), p90

    def footprint(self, frac: float, shape: Literal["rectangle", "hull"],
                  direction_rad: float | None = None) -> NDArray[np.float64] | None:
        """The footprint polygon (M, 2) from the kept cells (:meth:`kept`), less groups of them
        lying apart with neither a cell that reaches the 90th-percentile weight nor
        ``GROUP_MIN_SHARE`` of the weight (module doc), as their convex hull or bounding
        rectangle (least perimeter, or along ``direction_rad`` when given); None without
        evidence."""
        if len(self.weights) == 0:
            return None
        kept, p90 = self.kept(frac)
        c = cell_centres(self.keys[kept])
        # Grouped on coarser cells: the link is far above a cell, and large objects hold thousands.
        coarse_keys, cell_of = np.unique(cell_keys(c, GROUP_CELL_M), return_inverse=True)
        coarse = cell_centres(coarse_keys, GROUP_CELL_M)
        group = euclidean_clusters(np.column_stack([coarse, np.zeros(len(coarse))]), GROUP_LINK_M)[cell_of.reshape(-1)]
        w = self.weights[kept]
        well_seen = np.bincount(group, weights=(w >= p90).astype(np.float64)) > 0
        total = np.bincount(group, weights=w)
        c = c[well_seen[group] | (total[group] >= GROUP_MIN_SHARE * total.max())]
        h = CELL_M / 2
        hull = convex_footprint(c)  # of centres; each cell's half-width is added back
        corners = np.concatenate([hull + [-h, -h], hull + [h, -h], hull + [h, h], hull + [-h, h]])
        # The rectangle takes the hull of the corners itself: one hull, not two.
        if shape == "hull":
            return convex_footprint(corners)
        return min_perimeter_rectangle(corners) if direction_rad is None else rectangle_along(corners, direction_rad)


def view_quality(score: float, range_m: float, at_image_edge: bool, n_voxels: int, has_top: bool | None,
                 far_range_m: float, prior_fit: float = 1.0) -> float:
    """How much one observation says an object is there, in [0, 1]: the box score, the range,
    how much of the object the view holds (cut by the border, few voxels) and whether the 3D
    fit agrees with the class (``has_top``: a hollow class's top plane was found; None when
    the class has none; ``prior_fit``: how well its size fits the class, in [0, 1]). A close,
    clean, confident view is 1."""
    q = min(1.0, max(0.0, score) / QUALITY_FULL_SCORE)
    if range_m > QUALITY_NEAR_RANGE_M:
        t = min(1.0, (range_m - QUALITY_NEAR_RANGE_M) / max(1e-6, far_range_m - QUALITY_NEAR_RANGE_M))
        q *= 1.0 - (1.0 - QUALITY_FAR_WEIGHT) * t
    if at_image_edge:
        q *= QUALITY_EDGE_WEIGHT
    q *= min(1.0, n_voxels / QUALITY_FULL_VOXELS)
    if has_top is False:
        q *= QUALITY_NO_TOP_WEIGHT
    return q * min(1.0, max(0.0, prior_fit))
