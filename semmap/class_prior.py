"""Geometric class prior: what an object of each class measures, as evidence for its class.

A detector names a class from appearance; the map also knows how high the object stands and
how large its footprint is. Each class may state the ranges it lives in (``ClassConfig.prior``:
top height above the floor, footprint long and short side, metres). The top height is the
object's horizontal top plane where one was found (a table's top under the things on it, a
chair's seat), else its highest point. The object map weighs its
fused detector class probabilities by how well the measured object fits each class:

    p(class | votes, geometry) ∝ p(class | votes) * L(geometry | class)

``L`` is 1 inside every range and falls off as a Gaussian of the distance outside it, so a
"desk" 0.45 m high becomes a coffee table, a "chair" 2 m high is not believed, and a COCO
detector's one table class (mapped to ``desk``) becomes a coffee table or a conference table
when the measurement says so. Classes without a prior, or a measurement the object map does
not have yet, leave the votes as they are.

The geometry is not fused per frame: it is a property of the object's current estimate (its
top height and evidence footprint), so the prior is applied to the snapshot the map reports,
never accumulated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from semmap.config import ClassConfig, GeometricPrior
from semmap.polygons import min_perimeter_rectangle

#: How far outside its height range an object may measure before it counts strongly against
#: the class: the object map's top height is within 5 cm (p95) on simulated rooms.
HEIGHT_TOLERANCE_M = 0.03
#: The same for a footprint side above its range: footprints are within a few centimetres of
#: the truth once seen, and grow by depth noise at range.
FOOTPRINT_OVER_TOLERANCE_M = 0.10
#: One view's height above its class's range (see :func:`oversize_likelihood`).
VIEW_HEIGHT_TOLERANCE_M = 0.10
#: A table's top plane measured this far below its class's height range is another object's
#: top: the seat of a chair pushed in under it, in a cluster that missed the table top.
VIEW_TOP_UNDER_TOLERANCE_M = 0.10
#: A side below its range is weak evidence: part of an object is smaller than all of it, and
#: a table seen from one side maps short until the vehicle has flown round it.
FOOTPRINT_UNDER_TOLERANCE_M = 0.40
#: No class's likelihood goes below this, so a measurement no class fits leaves the votes to
#: decide instead of dividing zero by zero.
LIKELIHOOD_FLOOR = 1e-12


def footprint_sides_m(footprint_xy_m: NDArray[np.floating]) -> tuple[float, float] | None:
    """(long, short) sides of the least-perimeter rectangle around a footprint (M, 2), or None
    for fewer than 3 vertices."""
    poly = np.asarray(footprint_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(poly) < 3:
        return None
    rect = min_perimeter_rectangle(poly)
    a = float(np.hypot(*(rect[1] - rect[0])))
    b = float(np.hypot(*(rect[3] - rect[0])))
    return max(a, b), min(a, b)


def range_likelihood(value: float, bounds: tuple[float, float] | None, under_tol: float, over_tol: float) -> float:
    """1 inside ``bounds`` (or without bounds), else a Gaussian fall-off with the distance
    below (``under_tol``) or above (``over_tol``) the range."""
    if bounds is None or not math.isfinite(value):
        return 1.0
    lo, hi = bounds
    if value < lo:
        d = (lo - value) / under_tol
    elif value > hi:
        d = (value - hi) / over_tol
    else:
        return 1.0
    return math.exp(-0.5 * d * d)


def prior_likelihood(prior: GeometricPrior | None, height_m: float | None,
                     sides_m: tuple[float, float] | None) -> float:
    """How well one measured object fits one class's prior (1 = fully)."""
    if prior is None:
        return 1.0
    lik = 1.0
    if height_m is not None:
        lik *= range_likelihood(height_m, prior.height_m, HEIGHT_TOLERANCE_M, HEIGHT_TOLERANCE_M)
    if sides_m is not None:
        long_m, short_m = sides_m
        lik *= range_likelihood(long_m, prior.footprint_long_m, FOOTPRINT_UNDER_TOLERANCE_M,
                                FOOTPRINT_OVER_TOLERANCE_M)
        lik *= range_likelihood(short_m, prior.footprint_short_m, FOOTPRINT_UNDER_TOLERANCE_M,
                                FOOTPRINT_OVER_TOLERANCE_M)
    return lik


def oversize_likelihood(prior: GeometricPrior | None, height_m: float | None,
                        sides_m: tuple[float, float] | None) -> float:
    """How well one view fits under a class's upper bounds (1 = fully). A view shows part of
    an object, never more than all of it, so only measuring larger than the class counts:
    a "chair" 1.5 m high is a wall or a person, one 1.1 x 0.9 m holds the table it stands at.
    Per-view measurements are noisier than an object's fused estimate, hence the wider
    height tolerance."""
    if prior is None:
        return 1.0
    lik = 1.0
    if height_m is not None and prior.height_m is not None:
        lik *= range_likelihood(height_m, (0.0, prior.height_m[1]), 1.0, VIEW_HEIGHT_TOLERANCE_M)
    if sides_m is not None:
        for value, bounds in zip(sides_m, (prior.footprint_long_m, prior.footprint_short_m), strict=True):
            if bounds is not None:
                lik *= range_likelihood(value, (0.0, bounds[1]), 1.0, FOOTPRINT_OVER_TOLERANCE_M)
    return lik


def top_fits(prior: GeometricPrior | None, top_height_m: float) -> bool:
    """A table's measured top plane can be its top: not far below its class's height range (a
    top is a top however little of it is seen, unlike a side, which a partial view shortens)."""
    if prior is None or prior.height_m is None:
        return True
    return top_height_m >= prior.height_m[0] - VIEW_TOP_UNDER_TOLERANCE_M


class ClassPrior:
    """The configured classes' priors, in class order (see the module doc)."""

    def __init__(self, classes: Sequence[ClassConfig]) -> None:
        self.priors = [c.prior for c in classes]
        self.active = any(p is not None for p in self.priors)

    def likelihood(self, height_m: float | None, footprint_xy_m: NDArray[np.floating] | None) -> NDArray[np.float64]:
        """(K,) likelihood of the measured object under each class."""
        sides = footprint_sides_m(footprint_xy_m) if footprint_xy_m is not None else None
        lik = np.array([prior_likelihood(p, height_m, sides) for p in self.priors], dtype=np.float64)
        return np.maximum(lik, LIKELIHOOD_FLOOR)

    def posterior(self, class_probs: NDArray[np.floating], height_m: float | None,
                  footprint_xy_m: NDArray[np.floating] | None) -> NDArray[np.float64]:
        """(K,) class probabilities re-weighted by the measured geometry, normalised."""
        p = np.asarray(class_probs, dtype=np.float64)
        if not self.active:
            return p
        post = p * self.likelihood(height_m, footprint_xy_m)
        total = float(post.sum())
        return post / total if total > 0 else p
