"""The object map: association, Bayesian class fusion, existence and negative evidence."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semmap.config import MapConfig, default_classes
from semmap.frames import make_transform
from semmap.geometry import ObjectObservation
from semmap.objects import CameraView, ObjectMap
from semmap.polygons import convex_iou, grow_to_least_size, polygon_area_m2
from semmap.types import CameraIntrinsics

K = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
# Camera at the origin looking along map +x (optical z = map x, optical y = map -z).
T_MAP_CAMERA = make_transform(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                              np.array([0.0, 0.0, 0.5]))


def obs(track: int, cls: str = "chair", xy=(3.0, 0.0), score: float = 0.8, stamp: float = 0.0,
        size: float = 0.5) -> ObjectObservation:
    x, y = xy
    h = size / 2
    fp = np.array([[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h]])
    return ObjectObservation(track, cls, score, stamp, (x, y, 0.5), fp, 0.0, 0.9, 500, 100, 3.0)


def test_one_track_is_one_object_confirmed_after_two_sightings() -> None:
    m = ObjectMap(default_classes())
    m.update([obs(1)], 0.0)
    assert len(m) == 1 and not m.objects()[0].confirmed  # one sighting is not enough
    m.update([obs(1, xy=(3.02, 0.01), stamp=0.1)], 0.1)
    (o,) = m.objects()
    assert o.confirmed and o.n_observations == 2
    assert o.class_name == "chair"
    assert o.first_seen_s == 0.0 and o.last_seen_s == 0.1
    assert o.position_map_m[0] == pytest.approx(3.01, abs=0.011)


def test_a_new_track_on_a_known_object_is_reassociated() -> None:
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([obs(1, stamp=t)], float(t))
    ids = m.update([obs(2, xy=(3.1, 0.05), stamp=3.0)], 3.0)  # track lost, new id
    assert len(m) == 1 and ids == [m.objects()[0].object_id]
    m.update([obs(3, xy=(6.0, 0.0), stamp=4.0)], 4.0)  # elsewhere: another object
    assert len(m) == 2


def test_two_objects_in_one_frame_stay_apart() -> None:
    m = ObjectMap(default_classes())
    ids = m.update([obs(1, xy=(3.0, 0.0)), obs(2, xy=(3.0, 0.6))], 0.0)
    assert ids[0] != ids[1]


def test_class_probabilities_fuse_detector_scores() -> None:
    m = ObjectMap(default_classes())
    for t, (cls, s) in enumerate([("chair", 0.8), ("sofa", 0.6), ("chair", 0.7), ("chair", 0.8)]):
        m.update([obs(1, cls=cls, score=s, stamp=t)], float(t))
    (o,) = m.objects()
    assert o.class_name == "chair"
    assert o.class_probs["chair"] > 0.9
    assert sum(o.class_probs.values()) == pytest.approx(1.0)
    assert o.class_probs["sofa"] > o.class_probs["desk"]


def _view(depth_value: float) -> CameraView:
    depth = np.full((K.height_px, K.width_px), depth_value, np.float32)
    return CameraView(depth, K, T_MAP_CAMERA, (0.3, 6.0), tolerance_m=0.3)


def test_false_positive_fades_when_it_should_be_visible() -> None:
    m = ObjectMap(default_classes(), MapConfig(tentative_timeout_s=100.0))
    for t in range(4):
        m.update([obs(1, stamp=t)], float(t))
    assert m.objects()[0].confirmed
    t = 4.0
    while len(m) and t < 60:
        m.update([], t, view=_view(5.0))  # we see through where it should be
        t += 1.0
    assert len(m) == 0


def test_service_telemetry_pose_ci_desk_survives_a_second_of_misses_at_15_hz() -> None:
    # A confirmed desk went unseen by the detector in 10 frames at 15 Hz where the map expected
    # it; counted per frame, those misses took its existence from 0.98 to 0.38 in 0.7 s.
    m = ObjectMap(default_classes(), MapConfig(tentative_timeout_s=100.0))
    for k in range(10):
        m.update([obs(1, stamp=k / 15)], k / 15)
    assert m.objects()[0].confirmed
    for k in range(10, 25):
        m.update([], k / 15, view=_view(5.0))
    assert m.objects()[0].confirmed
    # The same misses over seconds still remove it.
    t = 25 / 15
    while len(m) and t < 30.0:
        t += 1 / 15
        m.update([], t, view=_view(5.0))
    assert len(m) == 0 and t < 15.0


def test_occluded_or_out_of_view_objects_keep_their_existence() -> None:
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([obs(1, stamp=t)], float(t))
    e0 = m.objects()[0].existence
    m.update([], 4.0, view=_view(1.0))  # something nearer hides it
    assert m.objects()[0].existence == pytest.approx(e0)
    behind = CameraView(np.full((240, 320), 5.0, np.float32), K,
                        make_transform(-T_MAP_CAMERA[:3, :3], np.array([0.0, 0.0, 0.5])))
    assert not behind.expects_visible(np.array([[3.0, 0.0, 0.5]]))[0]
    assert _view(5.0).expects_visible(np.array([[3.0, 0.0, 0.5]]))[0]


def test_unconfirmed_objects_time_out() -> None:
    m = ObjectMap(default_classes(), MapConfig(tentative_timeout_s=2.0))
    m.update([obs(99, cls="sofa", score=0.4)], 0.0)  # a weak sighting: tentative
    m.update([], 1.0)
    assert len(m) == 1
    m.update([], 3.0)
    assert len(m) == 0


def test_duplicate_detections_of_two_classes_merge() -> None:
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([obs(1, cls="desk", size=1.0, stamp=t)], float(t))
    m.update([obs(1, cls="desk", size=1.0, stamp=3), obs(2, cls="coffee_table", size=0.95, stamp=3)], 3.0)
    assert len(m) == 1


def test_footprints_and_json() -> None:
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([obs(1, stamp=t)], float(t))
    (fp,) = m.footprints()
    assert fp.margin_m == pytest.approx(0.20)
    assert fp.z_max_m == pytest.approx(0.9) and fp.existence > 0.6
    assert fp.polygon_xy_m.shape == (4, 2)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["objects"][0]["class_name"] == "chair"
    probs = m.class_probabilities()
    assert probs[fp.object_id].shape == (len(default_classes()),)


def test_unknown_class_is_a_clear_error() -> None:
    from semmap.errors import MapError

    with pytest.raises(MapError, match="'lamp'"):
        ObjectMap(default_classes()).update([obs(1, cls="lamp")], 0.0)


def test_dump_and_load_round_trip() -> None:
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([obs(1, stamp=t), obs(2, cls="desk", xy=(6.0, 1.0), size=1.0, stamp=t)], float(t))
    dump = json.loads(json.dumps(m.to_dict()))
    back = ObjectMap(default_classes())
    back.load_dict(dump)
    a, b = m.objects(), back.objects()
    assert [o.object_id for o in a] == [o.object_id for o in b]
    for x, y in zip(a, b, strict=True):
        assert x.class_name == y.class_name and x.existence == pytest.approx(y.existence, abs=1e-5)
        assert np.allclose(x.position_map_m, y.position_map_m, atol=1e-3)
        assert convex_iou(x.footprint_xy_m, y.footprint_xy_m) > 0.9
        assert x.z_max_m == pytest.approx(y.z_max_m, abs=1e-3)
    # New observations keep fusing into the restored objects.
    back.update([obs(9, xy=(3.05, 0.0), stamp=5.0)], 5.0)
    assert len(back) == 2


def test_load_rejects_a_dump_of_other_classes() -> None:
    from semmap.errors import MapError

    with pytest.raises(MapError, match="classes"):
        ObjectMap(default_classes()).load_dict({"classes": ["chair"], "objects": []})
    with pytest.raises(MapError, match="saved object #0"):
        ObjectMap(default_classes()).load_dict({"classes": [c.name for c in default_classes()],
                                                 "objects": [{"object_id": 1}]})


def _rect_obs(track: int, cls: str, x0: float, y0: float, x1: float, y1: float, z: tuple[float, float],
              top: float | None, stamp: float) -> ObjectObservation:
    fp = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    gx, gy = np.meshgrid(np.arange(x0 + 0.01, x1, 0.02), np.arange(y0 + 0.01, y1, 0.02))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    return ObjectObservation(track, cls, 0.8, stamp, ((x0 + x1) / 2, (y0 + y1) / 2, 0.3), fp, z[0], z[1], 500, 100,
                             2.0, top_height_m=top, points_xy_m=pts)


def test_a_box_showing_another_objects_surface_is_not_a_new_object() -> None:
    # Safety bench room 1037: a chair half-hidden behind a coffee table; the chair's box held
    # the table's points (top 0.43 m, z 0.21-0.44 m), and became a "chair" over the table that
    # closed the passage beside it. Also the table's own second track (its box on the table
    # in front) in the same frame as the table's own detection.
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.0, 0.6, (0.0, 0.44), 0.43, float(t))], float(t))
    (table,) = m.objects()
    for t in range(4, 10):
        ids = m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.0, 0.6, (0.0, 0.44), 0.43, float(t)),
                        _rect_obs(7, "chair", 3.05, 0.3, 3.45, 0.62, (0.21, 0.44), 0.43, float(t)),
                        _rect_obs(2, "coffee_table", 3.5, 0.05, 3.9, 0.5, (0.2, 0.45), 0.44, float(t))], float(t))
        assert ids == [table.object_id] * 3
    (o,) = m.objects()
    assert o.class_name == "coffee_table" and o.class_probs["coffee_table"] > 0.99
    # A chair tucked under a desk has a top of its own (its seat) and a backrest above the
    # desk: it stays an object of its own.
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([_rect_obs(1, "desk", 3.0, 0.0, 4.4, 0.7, (0.0, 0.73), 0.72, float(t))], float(t))
    for t in range(4, 7):
        m.update([_rect_obs(1, "desk", 3.0, 0.0, 4.4, 0.7, (0.0, 0.73), 0.72, float(t)),
                  _rect_obs(5, "chair", 3.4, 0.1, 3.9, 0.6, (0.0, 0.88), 0.45, float(t))], float(t))
    assert sorted(o.class_name for o in m.objects()) == ["chair", "desk"]


def test_an_object_that_turns_out_to_show_anothers_surface_is_merged_into_it() -> None:
    # The demo room: a coffee table seen half (top 0.48 m), and a second track on it named
    # "desk" whose first view had no top plane, so it became an object of its own (0.4 IoU
    # over the table, too little for the any-class merge). Once its views find the table's
    # top, it is the table's surface mapped twice: one object.
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.2, 0.45, (0.0, 0.49), 0.48, float(t))], float(t))
    (table,) = m.objects()
    ids = m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.2, 0.45, (0.0, 0.49), 0.48, 3.0),
                    _rect_obs(2, "desk", 3.2, 0.0, 3.68, 0.5, (0.0, 0.49), None, 3.0)], 3.0)
    assert len(m) == 2 and ids[1] != table.object_id  # no top plane yet: nothing says it is the table
    for t in range(4, 7):
        ids = m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.2, 0.45, (0.0, 0.49), 0.48, float(t)),
                        _rect_obs(2, "desk", 3.2, 0.0, 3.68, 0.5, (0.0, 0.49), 0.48, float(t))], float(t))
    assert ids == [table.object_id] * 2
    (o,) = m.objects()
    assert o.object_id == table.object_id and o.class_name == "coffee_table"  # the better-supported class
    # Same top but reaching higher (a chair's backrest above a table of seat height): apart.
    m = ObjectMap(default_classes())
    for t in range(3):
        m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.2, 0.45, (0.0, 0.49), 0.48, float(t))], float(t))
    m.update([_rect_obs(2, "chair", 3.2, 0.0, 3.68, 0.5, (0.0, 0.88), None, 3.0)], 3.0)
    for t in range(4, 7):
        m.update([_rect_obs(1, "coffee_table", 3.0, 0.0, 4.2, 0.45, (0.0, 0.49), 0.48, float(t)),
                  _rect_obs(2, "chair", 3.2, 0.0, 3.68, 0.5, (0.0, 0.88), 0.47, float(t))], float(t))
    assert sorted(o.class_name for o in m.objects()) == ["chair", "coffee_table"]


def test_duplicates_are_judged_on_the_footprint_of_every_view_not_the_latest_hull() -> None:
    # A desk seen whole only in views cut by the image border, then once uncut but only its
    # corner: its hull (the best views' outline) is that corner, its footprint (every view's
    # evidence) the whole desk. A second track over the whole desk, under another class and
    # with no top plane, is the same desk.
    import dataclasses

    m = ObjectMap(default_classes())
    for t in range(3):
        cut = dataclasses.replace(_rect_obs(1, "desk", 3.0, 0.0, 4.4, 0.7, (0.0, 0.73), None, float(t)),
                                  at_image_edge=True)
        m.update([cut], float(t))
    m.update([_rect_obs(1, "desk", 4.2, 0.5, 4.4, 0.7, (0.0, 0.73), None, 3.0)], 3.0)
    (desk,) = m.objects()
    assert np.ptp(desk.footprint_xy_m[:, 0]) > 1.3  # the whole desk
    ids = []
    for t in range(4, 7):
        ids = m.update([_rect_obs(2, "conference_table", 3.0, 0.0, 4.4, 0.7, (0.0, 0.73), None, float(t))], float(t))
    assert ids == [desk.object_id] and len(m) == 1


def test_one_box_over_two_objects_does_not_merge_them() -> None:
    # bench/mapping.py --quick, room 1000: a chair's track once had a box that held the coffee
    # table beside it too; the chair's hull (the union of its best views' outlines) grew over
    # the table, and the any-class overlap merge then swallowed the table into a 1.9 x 1.7 m
    # "chair". The footprints several views agree on still show two objects.
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([_rect_obs(2, "coffee_table", 3.6, 0.0, 4.6, 0.7, (0.0, 0.44), 0.43, float(t)),
                  _rect_obs(1, "chair", 3.0, 0.0, 3.5, 0.5, (0.0, 0.9), 0.45, float(t))], float(t))
    before = {o.class_name: o.object_id for o in m.objects()}
    assert len(before) == 2
    m.update([_rect_obs(1, "chair", 3.0, 0.0, 4.6, 0.7, (0.0, 0.9), 0.45, 4.0)], 4.0)
    assert len(m) == 2
    for t in range(5, 8):
        m.update([_rect_obs(2, "coffee_table", 3.6, 0.0, 4.6, 0.7, (0.0, 0.44), 0.43, float(t)),
                  _rect_obs(1, "chair", 3.0, 0.0, 3.5, 0.5, (0.0, 0.9), 0.45, float(t))], float(t))
    assert {o.class_name: o.object_id for o in m.objects()} == before  # the same two objects
    footprints = {o.class_name: o.footprint_xy_m for o in m.objects()}
    assert footprints["chair"][:, 0].max() < 3.6 and footprints["coffee_table"][:, 0].min() > 3.5


def test_grow_to_least_size_grows_on_the_unseen_side() -> None:
    # A 0.8 x 0.1 m sliver (a table top's near edge) seen by cameras to its north (+y).
    sliver = np.array([[0.0, 0.0], [0.8, 0.0], [0.8, 0.1], [0.0, 0.1]])
    grown = grow_to_least_size(sliver, (0.75, 0.45), away_from_xy=(0.0, -1.0))
    lo, hi = grown.min(axis=0), grown.max(axis=0)
    assert lo[0] == pytest.approx(0.0) and hi[0] == pytest.approx(0.8)  # long enough already
    assert hi[1] == pytest.approx(0.1) and lo[1] == pytest.approx(-0.35)  # all growth to the south
    assert polygon_area_m2(grown) == pytest.approx(0.8 * 0.45)
    # Seen from all round (no direction): even growth on both sides.
    even = grow_to_least_size(sliver, (0.75, 0.45))
    assert even[:, 1].min() == pytest.approx(-0.175) and even[:, 1].max() == pytest.approx(0.275)
    # Large enough: the polygon itself.
    big = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.6], [0.0, 0.6]])
    assert np.array_equal(grow_to_least_size(big, (0.75, 0.45), (0.0, -1.0)), big)


def test_planning_footprint_of_a_partly_seen_table_grows_away_from_the_camera() -> None:
    # A coffee table whose views (from a camera at y = +2 m) only showed a 0.1 m strip.
    m = ObjectMap(default_classes())
    fp = np.array([[2.6, 0.0], [3.4, 0.0], [3.4, 0.1], [2.6, 0.1]])
    for t in range(3):
        o = ObjectObservation(1, "coffee_table", 0.9, float(t), (3.0, 0.05, 0.4), fp, 0.0, 0.44, 500, 100, 2.0,
                              camera_xy_m=(3.0, 2.0))
        m.update([o], float(t))
    (mapped,) = m.objects()
    assert mapped.view_dir_xy[1] == pytest.approx(-1.0, abs=1e-6)
    measured = mapped.footprint_xy_m
    assert np.ptp(measured[:, 1]) < 0.2  # the map keeps what it measured (evidence cells)
    (planning,) = m.footprints()
    # Grown to the coffee table's least width, 0.45 m, all of it south (away from the camera).
    assert planning.polygon_xy_m[:, 1].max() == pytest.approx(measured[:, 1].max(), abs=1e-6)
    assert np.ptp(planning.polygon_xy_m[:, 1]) == pytest.approx(0.45, abs=1e-6)
    # A class without a least footprint keeps its measured one.
    classes = [c.model_copy(update={"min_footprint_m": None}) for c in default_classes()]
    m2 = ObjectMap(classes)
    for t in range(3):
        m2.update([ObjectObservation(1, "coffee_table", 0.9, float(t), (3.0, 0.05, 0.4), fp, 0.0, 0.44, 500, 100,
                                     2.0, camera_xy_m=(3.0, 2.0))], float(t))
    (p2,) = m2.footprints()
    assert np.ptp(p2.polygon_xy_m[:, 1]) < 0.2


def test_chairs_side_by_side_stay_two_after_one_box_held_both() -> None:
    # Chairs pushed in along a table: one chair's box once held its neighbour too, so its hull
    # grew over the neighbour; the neighbour's next track, and the shared seat height, must
    # not fold the two into one chair (bench/mapping.py --world realistic, room 1015).
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([_rect_obs(1, "chair", 3.0, 0.0, 3.5, 0.5, (0.0, 0.9), 0.45, float(t)),
                  _rect_obs(2, "chair", 3.6, 0.0, 4.1, 0.5, (0.0, 0.9), 0.45, float(t))], float(t))
    before = sorted(o.object_id for o in m.objects())
    assert len(before) == 2
    m.update([_rect_obs(1, "chair", 3.0, 0.0, 4.1, 0.5, (0.0, 0.9), 0.45, 4.0)], 4.0)
    for t in range(5, 9):
        # The neighbour's track was lost: a new track id, associated by its footprint.
        m.update([_rect_obs(1, "chair", 3.0, 0.0, 3.5, 0.5, (0.0, 0.9), 0.45, float(t)),
                  _rect_obs(10 + t, "chair", 3.6, 0.0, 4.1, 0.5, (0.0, 0.9), 0.45, float(t))], float(t))
    assert sorted(o.object_id for o in m.objects()) == before
    widths = sorted(float(np.ptp(o.footprint_xy_m[:, 0])) for o in m.objects())
    assert widths[-1] < 0.7  # neither footprint spans both chairs


def test_a_fragment_at_a_desks_far_end_is_merged_into_the_desk() -> None:
    # A desk whose views mostly showed its near part; two partial views of its far end became a
    # small "desk" of their own, apart from the desk's footprint but on the same top plane
    # (bench/mapping.py --world realistic, room 1001). Once the desk is seen again, one desk.
    m = ObjectMap(default_classes())
    for t in range(4):
        m.update([_rect_obs(1, "desk", 3.0, 0.0, 4.1, 0.7, (0.0, 0.74), 0.73, float(t))], float(t))
    for t in range(4, 6):
        m.update([_rect_obs(2, "desk", 4.3, 0.2, 4.46, 0.4, (0.0, 0.74), 0.73, float(t))], float(t))
    assert len(m.objects(confirmed_only=True)) == 2
    for t in range(6, 8):
        m.update([_rect_obs(1, "desk", 3.0, 0.0, 4.1, 0.7, (0.0, 0.74), 0.73, float(t))], float(t))
    (desk,) = m.objects()
    assert desk.n_observations == 8 and desk.class_name == "desk"


def test_a_fragment_on_a_table_top_is_merged_but_a_chair_beside_it_is_not() -> None:
    # A few chair boxes that showed only a patch of a conference table's top (chair backs
    # above its edge) became a tiny "chair" inside the table (room 1007); a real chair pushed
    # in at the table's side, seen as often, has a chair's footprint and stays.
    m = ObjectMap(default_classes())
    for t in range(5):
        m.update([_rect_obs(1, "conference_table", 3.0, 0.0, 4.8, 1.0, (0.0, 0.76), 0.75, float(t))], float(t))
    for t in range(5, 8):
        m.update([_rect_obs(1, "conference_table", 3.0, 0.0, 4.8, 1.0, (0.0, 0.76), 0.75, float(t)),
                  _rect_obs(2, "chair", 3.9, 0.8, 4.06, 0.96, (0.0, 0.98), 0.89, float(t)),
                  _rect_obs(3, "chair", 3.2, 0.8, 3.7, 1.3, (0.0, 0.95), 0.46, float(t))], float(t))
    assert len(m.objects(confirmed_only=True)) == 3
    for t in range(8, 10):
        m.update([_rect_obs(1, "conference_table", 3.0, 0.0, 4.8, 1.0, (0.0, 0.76), 0.75, float(t))], float(t))
    assert sorted(o.class_name for o in m.objects()) == ["chair", "conference_table"]
    (chair,) = [o for o in m.objects() if o.class_name == "chair"]
    assert chair.footprint_xy_m[:, 1].max() > 1.2  # the pushed-in chair, not the fragment
