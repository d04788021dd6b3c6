"""Footprint evidence and the object map's footprint and confirmation rules (regressions from
bench/mapping.py: chairs turned by 45 degrees, walls behind far whiteboards confirmed)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.camera_view import CameraView
from semmap.config import MapConfig, default_classes
from semmap.geometry import ObjectObservation
from semmap.object_evidence import CELL_M, FootprintEvidence
from semmap.objects import ObjectMap
from semmap.pointcloud import backproject
from semmap.polygons import convex_footprint, min_perimeter_rectangle, polygon_area_m2
from tests.unit.test_geometry import FLOOR, K, camera_pose, render


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


def _sparse_views_of_a_table(rng: np.random.Generator, n_views: int, centre_xy: tuple[float, float],
                             size_m: tuple[float, float], yaw_rad: float) -> list[np.ndarray]:
    """Views of a table top as a low-resolution camera at 3 m samples it: each view a few
    dozen of its points (3 cm voxels, jittered), so most 2 cm cells are hit by a few views."""
    views = []
    for _ in range(n_views):
        n = int(rng.integers(50, 150))
        local = (rng.random((n, 2)) - 0.5) * np.asarray(size_m)
        views.append(_rotate(local, yaw_rad) + np.asarray(centre_xy))
    return views


def test_stray_cells_seen_twice_far_from_an_object_do_not_stretch_its_footprint() -> None:
    # A coffee table's views at range sometimes hold the wall behind it (joined to the top by
    # flying pixels); wall points recur in a few views from one place, so their cells reach
    # the kept weight of the table's sparsely hit cells.
    rng = np.random.default_rng(5)
    centre, size, yaw = (-3.46, 0.45), (0.82, 0.51), 0.957
    ev = FootprintEvidence()
    wall = np.column_stack([np.full(12, -5.05), np.linspace(0.3, 0.9, 12)])
    for i, view in enumerate(_sparse_views_of_a_table(rng, 25, centre, size, yaw)):
        ev.add_view(np.vstack([view, wall]) if i in (10, 13, 17) else view, 1.0)
    fp = ev.footprint(0.65, "rectangle")
    assert fp is not None
    assert np.linalg.norm(fp.mean(axis=0) - np.asarray(centre)) < 0.05
    assert polygon_area_m2(fp) < 1.3 * size[0] * size[1]


def test_two_well_seen_parts_of_one_object_both_stay_in_its_footprint() -> None:
    # The two ends of a long table, each seen by many views from its own side, the middle by
    # few: both ends are the table.
    ev = FootprintEvidence()
    gx, gy = np.meshgrid(np.arange(0.0, 0.5, 0.01), np.arange(0.0, 0.8, 0.01))
    end = np.column_stack([gx.ravel(), gy.ravel()])
    for _ in range(10):
        ev.add_view(end, 1.0)
        ev.add_view(end + [1.5, 0.0], 0.8)
    fp = ev.footprint(0.65, "rectangle")
    assert fp is not None
    assert fp.min(axis=0) == pytest.approx([0.0, 0.0], abs=CELL_M)
    assert fp.max(axis=0) == pytest.approx([2.0, 0.8], abs=CELL_M)


def test_a_coffee_table_keeps_its_class_and_place_when_a_few_views_hold_the_wall_behind_it() -> None:
    # Its footprint stretched to the wall is a sofa's size: the class prior then named it a
    # sofa, centred half a metre behind the table.
    rng = np.random.default_rng(7)
    centre, size, yaw = (-3.46, 0.45), (0.82, 0.51), 0.957
    wall = np.column_stack([np.full(12, -5.05), np.linspace(0.3, 0.9, 12)])
    m = ObjectMap(default_classes(), MapConfig())
    for i, view in enumerate(_sparse_views_of_a_table(rng, 25, centre, size, yaw)):
        pts = np.vstack([view, wall]) if i in (10, 13, 17) else view
        c = pts.mean(axis=0)
        m.update([ObjectObservation(1, "coffee_table", 0.9, 0.1 * i, (c[0], c[1], 0.3), convex_footprint(pts),
                                    0.0, 0.48, 400, len(pts), 3.3, top_height_m=0.47, points_xy_m=pts,
                                    camera_xy_m=(-0.3, 0.0))], 0.1 * i)
    (o,) = m.objects()
    assert o.class_name == "coffee_table"
    assert np.linalg.norm(o.footprint_center_xy_m - np.asarray(centre)) < 0.05


def test_a_seat_hidden_under_a_table_in_most_views_keeps_its_footprint() -> None:
    # A chair pushed in under a table's edge: the table top hides most of the seat from the
    # views that see the backrest. By weight alone the chair was a strip along its backrest;
    # the views that could not see the seat do not count against it.
    table_top = ((-1.0, -0.6, 0.72), (0.35, 0.6, 0.75))
    seat, back = ((0.0, -0.25, 0.42), (0.5, 0.25, 0.45)), ((0.5, -0.25, 0.45), (0.55, 0.25, 0.95))
    stray = np.array([[0.25, 0.45, 0.02]])  # a floor point beside the chair, in plain view
    seen, by_weight = FootprintEvidence(), FootprintEvidence()
    for k in range(36):
        a = math.radians(-180.0 + 360.0 * k / 35)
        cx, cy = 0.3 + 1.8 * math.cos(a), 1.8 * math.sin(a)
        T = camera_pose(cx, cy, 1.5, math.atan2(-cy, 0.3 - cx), 30.0)
        depth = render([table_top, seat, back, FLOOR], T)
        pc, _ = backproject(depth, K, 0.3, 8.0)
        pts = pc.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        on_chair = np.zeros(len(pts), dtype=bool)
        for lo, hi in (seat, back):
            on_chair |= np.all((pts >= np.asarray(lo) - 0.01) & (pts <= np.asarray(hi) + 0.01), axis=1)
        pts = np.vstack([pts[on_chair], stray]) if k % 12 == 0 else pts[on_chair]
        seen.add_view(pts, 1.0, CameraView(depth, K, T, (0.3, 8.0)))
        by_weight.add_view(pts[:, :2], 1.0)
    strip = by_weight.footprint(0.65, "rectangle")
    assert strip is not None and np.ptp(strip[:, 0]) < 0.15  # the backrest only
    fp = seen.footprint(0.65, "rectangle")
    assert fp is not None
    assert fp.min(axis=0) == pytest.approx([0.0, -0.25], abs=0.12)
    assert fp.max(axis=0) == pytest.approx([0.55, 0.25], abs=0.03)  # the stray point is not the chair's


def test_merged_evidence_keeps_the_views_that_could_see_each_cell() -> None:
    a, b = FootprintEvidence(), FootprintEvidence()
    a.add_view(np.array([[0.01, 0.01, 0.4]]), 1.0)
    b.add_view(np.array([[0.01, 0.01, 0.5], [0.05, 0.01, 0.3]]), 0.5)
    a.merge(b)
    assert a.weights.tolist() == [1.5, 0.5] and a.visible.tolist() == [1.5, 0.5]
    assert a.top_z_m.tolist() == pytest.approx([0.5, 0.3]) and a.total_weight == 1.5
