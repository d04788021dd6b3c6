"""Footprint evidence and the object map's footprint and confirmation rules (regressions from
bench/mapping.py: chairs turned by 45 degrees, walls behind far whiteboards confirmed)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.config import MapConfig, default_classes
from semmap.geometry import ObjectObservation
from semmap.object_evidence import CELL_M, FootprintEvidence
from semmap.objects import ObjectMap
from semmap.polygons import min_perimeter_rectangle, polygon_area_m2


def _rotate(xy: np.ndarray, yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return xy @ np.array([[c, -s], [s, c]]).T


def _side_directions_deg(rect: np.ndarray) -> set[int]:
    e = np.diff(np.vstack([rect, rect[:1]]), axis=0)
    return {round(math.degrees(math.atan2(y, x))) % 90 for x, y in e}


@pytest.mark.parametrize("yaw_deg", [0.0, 17.0, 55.0])
def test_l_shaped_cells_give_the_rectangle_along_the_legs_not_the_diagonal(yaw_deg: float) -> None:
    # A chair's backrest (seen by every view) and one side of its seat, the corner leg
    # between them missing: an L whose hull is nearly a right triangle. Its least-area
    # rectangle is turned by 44 degrees, the centre 14.5 cm off.
    back = np.column_stack([np.zeros(22), np.linspace(0.04, 0.46, 22)])
    side = np.column_stack([np.linspace(0.04, 0.44, 21), np.zeros(21)])
    pts = _rotate(np.vstack([back, side]), math.radians(yaw_deg))
    rect = min_perimeter_rectangle(pts)
    assert _side_directions_deg(rect) == {round(yaw_deg) % 90}
    assert polygon_area_m2(rect) == pytest.approx(0.44 * 0.46, rel=0.02)
    centre = _rotate(np.array([[0.22, 0.23]]), math.radians(yaw_deg))[0]
    assert np.linalg.norm(rect.mean(axis=0) - centre) < 0.01


def test_filled_rectangle_keeps_its_orientation() -> None:
    gx, gy = np.meshgrid(np.linspace(-0.7, 0.7, 40), np.linspace(-0.35, 0.35, 20))
    pts = _rotate(np.column_stack([gx.ravel(), gy.ravel()]), math.radians(30.0))
    rect = min_perimeter_rectangle(pts)
    assert _side_directions_deg(rect) == {30}
    assert polygon_area_m2(rect) == pytest.approx(1.4 * 0.7, rel=0.01)


def test_evidence_footprint_ignores_cells_few_views_saw() -> None:
    ev = FootprintEvidence()
    gx, gy = np.meshgrid(np.arange(0.0, 0.5, 0.01), np.arange(0.0, 0.4, 0.01))
    square = np.column_stack([gx.ravel(), gy.ravel()])
    for _ in range(10):
        ev.add_view(square, 1.0)
    ev.add_view(np.array([[1.0, 1.0]]), 1.0)  # one stray point, one view
    fp = ev.footprint(0.65, "rectangle")
    assert fp is not None
    assert fp.max(axis=0) == pytest.approx([0.5, 0.4], abs=CELL_M)
    merged = FootprintEvidence()
    merged.merge(ev)
    assert np.array_equal(merged.keys, ev.keys) and np.array_equal(merged.weights, ev.weights)


def _obs(stamp: float, range_m: float) -> ObjectObservation:
    fp = np.array([[2.0, -0.9], [2.2, -0.9], [2.2, 0.9], [2.0, 0.9]])
    return ObjectObservation(1, "whiteboard", 0.8, stamp, (2.1, 0.0, 0.4), fp, 0.0, 0.6, 900, 400, range_m)


def test_views_beyond_the_footprint_range_alone_do_not_confirm_an_object() -> None:
    cfg = MapConfig(tentative_timeout_s=2.0)
    m = ObjectMap(default_classes(), cfg)
    for i in range(6):  # far views: the wall behind a half-hidden whiteboard, say
        m.update([_obs(0.1 * i, cfg.footprint_max_range_m + 1.5)], 0.1 * i)
    (o,) = m.objects()
    assert not o.confirmed and o.existence < cfg.existence_confirm
    m.update([], 3.0)  # unconfirmed and not seen again: it times out
    assert len(m) == 0
    # One nearer view confirms what far views had seen.
    m = ObjectMap(default_classes(), cfg)
    for i in range(3):
        m.update([_obs(0.1 * i, cfg.footprint_max_range_m + 1.5)], 0.1 * i)
    m.update([_obs(0.4, cfg.footprint_max_range_m - 1.0)], 0.4)
    assert m.objects()[0].confirmed
