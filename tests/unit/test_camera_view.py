"""Footprint edges the field of view drew: marked per view, and kept out of the rectangle's direction."""

from __future__ import annotations

import math

import numpy as np

from semmap.camera_view import EdgeDirections, cut_edges, depth_frame_px
from semmap.config import GeometryConfig, default_classes
from semmap.frame_objects import observe_frame
from semmap.objects import ObjectMap
from semmap.types import Track
from tests.unit.test_geometry import FLOOR, K, box_of, camera_pose, render
from tests.unit.test_touching_furniture import TABLE

CLASSES = {c.name: c for c in default_classes()}


def _view(T: np.ndarray, whole_image: bool = False) -> list:
    depth = render(TABLE + [FLOOR], T)
    # A table filling the view: the detector's box is the image (box_of's corners are behind the camera).
    box = (0.0, 0.0, float(K.width_px), float(K.height_px)) if whole_image else box_of(TABLE, T)
    track = Track(1, box, 0.9, "desk")
    return observe_frame(depth, K, T, [track], {"desk": CLASSES["desk"]}, GeometryConfig(), depth_range_m=(0.3, 8.0))


def _off_axis_deg(rectangle_xy_m: np.ndarray) -> float:
    """How far a rectangle's sides turn from the map axes, which the table's run along."""
    e = rectangle_xy_m[1] - rectangle_xy_m[0]
    a = math.degrees(math.atan2(e[1], e[0])) % 90.0
    return min(a, 90.0 - a)


def test_a_table_cut_by_the_image_corner_keeps_its_own_edge_directions() -> None:
    # Low over the table's corner, looking down steeply: the image's corner cuts the top
    # diagonally, and a least-perimeter rectangle turned 33 deg towards the cut.
    obs = _view(camera_pose(1.8, -0.6, 1.4, math.radians(30.0), 60.0), whole_image=True)
    assert len(obs) == 1 and obs[0].footprint_edge_cut is not None and obs[0].footprint_edge_cut.any()
    m = ObjectMap(default_classes())
    m.update(obs, 0.0)
    (table,) = m.objects(confirmed_only=False)
    assert _off_axis_deg(table.footprint_xy_m) < 3.0


def test_only_edges_along_the_depth_image_border_are_cut() -> None:
    whole = _view(camera_pose(1.0, -0.4, 1.4, math.radians(35.0), 35.0))[0]
    assert whole.footprint_edge_cut is not None and not whole.footprint_edge_cut.any()
    T = camera_pose(1.8, -0.6, 1.4, math.radians(30.0), 60.0)
    cut = _view(T, whole_image=True)[0]
    fp, flags = cut.footprint_xy_m, cut.footprint_edge_cut
    assert flags is not None
    mid = (fp + np.roll(fp, -1, axis=0)) / 2
    # The table's own sides (x = 2.0, y = 0.0) are never cut; the rest of the outline is the image's.
    on_table_side = (np.abs(mid[:, 0] - 2.0) < 0.05) | (np.abs(mid[:, 1]) < 0.05)
    assert on_table_side.any() and not flags[on_table_side].any()
    assert flags[~on_table_side].all()
    # A registered depth image with invalid bands: its border is where the bands begin.
    depth = render(TABLE + [FLOOR], T)
    depth[:, -30:] = 0.0
    assert depth_frame_px(depth, 0.3, 8.0)[2] == K.width_px - 31
    inner = cut_edges(fp, cut.voxels_map_m, K, T, depth_frame_px(depth, 0.3, 8.0), 0.03, 2)
    assert inner.sum() >= flags.sum()


def test_an_outline_without_cuts_leaves_the_rectangle_to_the_least_perimeter_fit() -> None:
    c, s = math.cos(math.radians(10.0)), math.sin(math.radians(10.0))
    along, across = np.array([c, s]), np.array([-s, c])
    rotated = np.array([[0.0, 0.0], along, along + 0.5 * across, 0.5 * across])  # 1.0 x 0.5 m at 10 deg
    edges = EdgeDirections()
    edges.add_view(rotated, np.zeros(4, dtype=bool))
    assert edges.rectangle_direction_rad() is None
    # The same object seen again with its far half cut off at 40 deg by the image's border.
    w = np.array([math.cos(math.radians(40.0)), math.sin(math.radians(40.0))])
    edges.add_view(np.array([[0.0, 0.0], 0.6 * along, 0.6 * along + 0.5 * w, 0.5 * across]),
                   np.array([False, True, False, False]))
    direction = edges.rectangle_direction_rad()
    assert direction is not None and abs(math.degrees(direction) - 10.0) < 1.0
