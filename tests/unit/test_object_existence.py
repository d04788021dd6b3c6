"""Existence from the quality of the views, misses only where a detection was due, and the
duplicate merge that keeps the better-supported object."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from semmap.config import MapConfig, default_classes
from semmap.frames import make_transform
from semmap.object_evidence import view_quality
from semmap.object_state import logit
from semmap.objects import CameraView, ObjectMap
from tests.unit.test_objects import T_MAP_CAMERA, K, obs

TABLE_CLASSES = {"desk", "coffee_table", "conference_table"}


def test_one_close_clean_view_confirms_and_weak_glimpses_do_not() -> None:
    m = ObjectMap(default_classes())
    m.update([dataclasses.replace(obs(1, cls="sofa", score=0.85), range_m=2.0)], 0.0)
    assert m.objects()[0].confirmed
    weak = ObjectMap(default_classes())
    glimpse = dataclasses.replace(obs(1, cls="sofa", score=0.35), range_m=3.9, at_image_edge=True, n_voxels=25)
    weak.update([glimpse], 0.0)
    assert not weak.objects()[0].confirmed
    assert view_quality(0.35, 3.9, True, 25, None, 4.0) < 0.2 < view_quality(0.85, 2.0, False, 100, None, 4.0)


def test_a_miss_counts_only_where_the_object_is_near_enough_to_be_detected() -> None:
    m = ObjectMap(default_classes(), MapConfig(footprint_max_range_m=4.0))
    far = obs(1, cls="sofa", xy=(5.0, 0.0))  # its views were near (range_m 3), it is 5 m from this camera
    for t in range(3):
        m.update([dataclasses.replace(far, stamp_s=float(t))], float(t))
    e0 = m.objects()[0].existence
    clear = CameraView(np.full((K.height_px, K.width_px), 6.0, np.float32), K, T_MAP_CAMERA, (0.3, 6.0))
    assert clear.expects_visible(np.array([[5.0, 0.0, 0.5]]))[0]  # in view, not hidden
    for t in range(3, 8):
        m.update([], float(t), view=clear)
    assert m.objects()[0].existence == e0
    near = CameraView(clear.depth_m, K, make_transform(T_MAP_CAMERA[:3, :3], np.array([2.0, 0.0, 0.5])),
                      (0.3, 6.0))
    m.update([], 8.0, view=near)  # 3 m away and in view: this miss counts
    assert m.objects()[0].existence < e0


def test_a_duplicate_merge_keeps_the_better_supported_object_and_weighs_class_evidence() -> None:
    m = ObjectMap(default_classes())
    # One frame, two boxes over one table: a confident "chair" box that saw a sliver of it at
    # the image border, and a "desk" box that saw all of it.
    sliver = dataclasses.replace(obs(1, cls="chair", score=0.9, size=1.0), at_image_edge=True, n_voxels=12)
    whole = dataclasses.replace(obs(2, cls="desk", score=0.8, size=1.0, xy=(3.02, 0.0)), n_voxels=200,
                                top_height_m=0.74)
    ids = m.update([sliver, whole], 0.0)
    (o,) = m.objects()
    # The sliver came first (higher score) and has the lower id; the whole view is kept.
    assert ids == [2, 2] and o.object_id == 2
    assert o.class_name in TABLE_CLASSES


def test_a_second_box_of_the_same_object_and_class_in_one_frame_counts_as_a_detection() -> None:
    def box(track: int) -> object:
        return dataclasses.replace(obs(track, cls="chair", score=0.45), top_height_m=0.45, range_m=1.5)

    one, two = ObjectMap(default_classes()), ObjectMap(default_classes())
    one.update([box(1)], 0.0)
    ids = two.update([box(1), box(2)], 0.0)
    assert len(two) == 1 and ids[0] == ids[1]
    assert not one.objects()[0].confirmed and two.objects()[0].confirmed


def test_a_long_table_seen_from_its_other_end_is_one_table() -> None:
    m = ObjectMap(default_classes())
    near_end = np.array([[2.0, 0.0], [3.0, 0.0], [3.0, 1.0], [2.0, 1.0]])
    first = dataclasses.replace(obs(1, cls="desk", xy=(2.5, 0.5), size=1.0), footprint_xy_m=near_end,
                                top_height_m=0.73, z_max_m=0.75)
    m.update([first], 0.0)
    # The far end, from elsewhere: the same top plane, overlapping the first part at the seam only.
    far_end = np.array([[2.9, 0.0], [4.0, 0.0], [4.0, 1.0], [2.9, 1.0]])
    second = dataclasses.replace(obs(2, cls="desk", xy=(3.45, 0.5), size=1.0), footprint_xy_m=far_end,
                                 top_height_m=0.74, z_max_m=0.76, stamp_s=1.0)
    m.update([second], 1.0)
    assert len(m) == 1
    # A different top beside it (a coffee table's 0.45 m) is another object.
    low = dataclasses.replace(second, track_id=3, top_height_m=0.45, z_max_m=0.47, stamp_s=2.0)
    m.update([low], 2.0)
    assert len(m) == 2


def test_a_track_that_moved_off_its_object_joins_the_object_its_view_overlaps() -> None:
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([obs(1, cls="desk", xy=(3.0, 0.0), size=1.0, stamp=t)], float(t))
    (desk,) = m.objects()
    # A new track first sees something just beyond the desk's end...
    m.update([obs(2, cls="desk", xy=(3.9, 0.0), size=0.2, stamp=3)], 3.0)
    assert len(m) == 2
    # ...then its box slides onto the desk: that view is the desk's, not the corner's.
    ids = m.update([obs(2, cls="desk", xy=(3.2, 0.0), size=0.5, stamp=4)], 4.0)
    assert ids == [desk.object_id]


def test_one_view_larger_than_its_class_does_not_confirm_it() -> None:
    # A view shows part of an object, never more: one larger than any object of its class is
    # something else in the box (a wall, the table the chair stands at), however clean.
    chair = dataclasses.replace(obs(1, cls="chair", score=0.85), range_m=2.0, z_max_m=0.9, top_height_m=0.45)
    tall = dataclasses.replace(chair, z_max_m=1.46, top_height_m=None)
    wide = dataclasses.replace(obs(1, cls="chair", score=0.85, size=1.2), range_m=2.0, z_max_m=0.9,
                               top_height_m=0.45)
    for view, confirmed in ((chair, True), (tall, False), (wide, False)):
        m = ObjectMap(default_classes())
        m.update([view], 0.0)
        assert m.objects()[0].confirmed is confirmed, view
    # A detector class standing for several of ours fits the largest of them: COCO's one table
    # class names a 2.0 x 1.1 m dining table "desk" (at most 2.0 x 0.95 m).
    classes = default_classes()
    votes = {"desk": ("desk", "coffee_table", "conference_table")}
    table = dataclasses.replace(obs(1, cls="desk", score=0.85, size=1.1), range_m=2.0, z_max_m=0.75,
                                top_height_m=0.75)
    assert not _confirmed_by(ObjectMap(classes), table)
    assert _confirmed_by(ObjectMap(classes, vote_groups=votes), table)


def _confirmed_by(m: ObjectMap, view: object) -> bool:
    m.update([view], 0.0)  # type: ignore[list-item]
    return bool(m.objects()[0].confirmed)


def test_a_table_view_whose_top_is_a_chair_seat_adds_no_geometry() -> None:
    # The table's box held only a chair pushed in under it: the top plane found is the seat.
    classes = default_classes()
    table = dataclasses.replace(obs(1, cls="conference_table", score=0.85, xy=(3.0, 0.0), size=1.0),
                                range_m=2.0, z_max_m=0.77, top_height_m=0.75)
    seat = dataclasses.replace(obs(1, cls="conference_table", score=0.85, xy=(3.55, 0.0), size=0.5),
                               range_m=2.0, z_max_m=0.5, top_height_m=0.47, stamp_s=0.1)
    m = ObjectMap(classes)
    m.update([table], 0.0)
    before = m.objects(confirmed_only=False)[0].footprint_xy_m
    m.update([seat], 0.1)
    (o,) = m.objects(confirmed_only=False)
    assert o.n_observations == 2  # the detection still counts
    assert np.max(o.footprint_xy_m[:, 0]) == pytest.approx(np.max(before[:, 0]), abs=0.02)
    # The same view of a coffee table, whose top is at seat height, is its geometry.
    low = ObjectMap(classes)
    low.update([dataclasses.replace(table, class_name="coffee_table", top_height_m=0.45, z_max_m=0.47)], 0.0)
    low.update([dataclasses.replace(seat, class_name="coffee_table")], 0.1)
    assert np.max(low.objects(confirmed_only=False)[0].footprint_xy_m[:, 0]) > np.max(before[:, 0]) + 0.1


def _missed_from(cameras_y_m: list[float], dt_s: float) -> float:
    """Existence log-odds lost by a well-seen sofa at (3, 0) missed once from each camera (at y,
    facing +x), ``dt_s`` apart."""
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([dataclasses.replace(obs(1, cls="sofa"), stamp_s=float(t))], float(t))
    e0 = logit(m.objects()[0].existence)
    depth = np.full((K.height_px, K.width_px), 6.0, np.float32)
    for i, y in enumerate(cameras_y_m):
        T = make_transform(T_MAP_CAMERA[:3, :3], np.array([0.0, y, 0.5]))
        m.update([], 3.0 + i * dt_s, view=CameraView(depth, K, T, (0.3, 6.0)))
    return e0 - logit(m.objects()[0].existence)


def test_misses_from_keyframes_count_each_and_video_frames_from_one_place_count_once() -> None:
    # Video: 15 Hz from one place, the frames miss for the same reason.
    video = _missed_from([0.0] * 4, 1.0 / 15.0)
    # Keyframes a camera step apart, stamped as closely: four views, four misses.
    keyframes = _missed_from([0.0, 0.3, 0.6, 0.9], 1.0 / 15.0)
    one = _missed_from([0.0], 1.0)
    assert one > 0.0
    assert video < 1.5 * one
    assert keyframes > 3.5 * one

