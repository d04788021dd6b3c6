"""Detector dataset generator: labels from masks, YOLO lines, split seeds, camera poses."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import SimulationError
from companion.sim.dataset import (
    MAX_ROOMS_PER_SPLIT,
    DatasetSpec,
    generate,
    labels_from_instance_mask,
    room_seeds,
    sample_camera_pose,
    varied_room,
    write_dataset,
    yolo_label_lines,
)
from companion.sim.groundtruth import clearance_m
from semmap.frames import rpy_from_rotation
from semmap.types import CameraIntrinsics

SMALL = CameraIntrinsics(96.0, 96.0, 80.0, 60.0, 160, 120)


def test_labels_are_tight_boxes_of_visible_pixels_and_small_objects_are_dropped() -> None:
    inst = np.zeros((50, 80), dtype=np.int32)
    cls = np.full((50, 80), -1, dtype=np.int16)
    inst[10:20, 30:45] = 3  # 150 px
    cls[10:20, 30:45] = 2
    inst[40:42, 0:5] = 7  # 10 px: below the threshold
    cls[40:42, 0:5] = 0
    inst[0:30, 70:80] = 9  # building-less object without a class: never labelled
    boxes, classes, px, ids = labels_from_instance_mask(inst, cls, min_visible_px=100)
    np.testing.assert_array_equal(boxes, [[30, 10, 45, 20]])
    np.testing.assert_array_equal(classes, [2])
    np.testing.assert_array_equal(px, [150])
    np.testing.assert_array_equal(ids, [3])


def test_empty_mask_gives_empty_arrays() -> None:
    boxes, classes, px, ids = labels_from_instance_mask(
        np.zeros((4, 4), np.int32), np.full((4, 4), -1, np.int16), 1
    )
    assert boxes.shape == (0, 4) and classes.shape == (0,) and px.shape == (0,) and ids.shape == (0,)


@given(
    u0=st.integers(0, 600), v0=st.integers(0, 400), w=st.integers(1, 40), h=st.integers(1, 80),
    c=st.integers(0, 5),
)
def test_yolo_line_round_trips_the_box(u0: int, v0: int, w: int, h: int, c: int) -> None:
    (line,) = yolo_label_lines(np.array([[u0, v0, u0 + w, v0 + h]], float), np.array([c]), 640, 480)
    k, cx, cy, bw, bh = line.split()
    assert int(k) == c
    assert float(cx) * 640 - float(bw) * 640 / 2 == pytest.approx(u0, abs=1e-3)
    assert float(cy) * 480 + float(bh) * 480 / 2 == pytest.approx(v0 + h, abs=1e-3)


def test_split_room_seeds_are_disjoint() -> None:
    n = MAX_ROOMS_PER_SPLIT
    train, val, heldout = (set(room_seeds(s, n)) for s in ("train", "val", "heldout"))
    assert not train & val and not train & heldout and not val & heldout
    with pytest.raises(SimulationError, match="at most"):
        room_seeds("train", n + 1)
    with pytest.raises(SimulationError, match="at most"):
        list(generate(DatasetSpec(split="train", n_rooms=2, intrinsics=SMALL), room_start=n - 1))
    with pytest.raises(SimulationError, match="split"):
        room_seeds("validation", 3)
    with pytest.raises(SimulationError, match="split"):
        DatasetSpec(split="test")


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_camera_poses_fly_inside_the_room_clear_of_furniture(seed: int) -> None:
    spec = DatasetSpec()
    rng = np.random.default_rng(seed)
    room = varied_room(100_000 + seed % 50, rng, spec.class_names)
    for _ in range(5):
        T = sample_camera_pose(room, spec, rng)
        x, y, z = T[:3, 3]
        assert 0.0 < x < room.width_m and 0.0 < y < room.depth_m
        assert spec.height_range_m[0] <= z <= min(spec.height_range_m[1], room.wall_height_m)
        assert clearance_m(room, T[None, :3, 3], 0.2)[0] >= spec.min_clearance_m
        # Optical z (forward) to body FLU: roll about the optical axis stays within limits,
        # and the view never points more than 60 degrees down or 20 degrees up.
        fwd = T[:3, 2]
        pitch_down_deg = math.degrees(math.asin(-fwd[2]))
        assert -20.0 - 1e-6 <= pitch_down_deg <= 60.0 + 1e-6
        R_body = T[:3, :3] @ np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
        roll, _, _ = rpy_from_rotation(R_body)
        assert abs(math.degrees(roll)) <= spec.max_roll_pitch_deg + 1e-6


def test_generated_images_are_labelled_from_the_rendered_masks(tmp_path) -> None:  # type: ignore[no-untyped-def]
    spec = DatasetSpec(split="heldout", n_rooms=1, images_per_room=3, intrinsics=SMALL, min_visible_px=20)
    items = list(generate(spec))
    assert len(items) == 3
    assert len({it.name for it in items}) == 3
    n_labels = 0
    for it in items:
        assert it.rgb.shape == (120, 160, 3) and it.rgb.dtype == np.uint8
        assert it.room_seed == room_seeds("heldout", 1)[0]
        b = it.boxes_xyxy_px
        assert np.all(b[:, 0] >= 0) and np.all(b[:, 2] <= 160) and np.all(b[:, 3] <= 120)
        assert np.all(b[:, 2] > b[:, 0]) and np.all(b[:, 3] > b[:, 1])
        assert np.all((it.class_ids >= 0) & (it.class_ids < len(spec.class_names)))
        assert np.all(it.visible_px >= 20)
        n_labels += len(b)
    assert n_labels > 0  # poses are aimed at furniture most of the time
    # Same spec, same images (the dataset is reproducible).
    again = next(iter(generate(spec)))
    np.testing.assert_array_equal(again.rgb, items[0].rgb)

    counts = write_dataset(spec, tmp_path)
    assert counts["images"] == 3 and counts["labels"] == n_labels
    assert len(list((tmp_path / "images" / "heldout").glob("*.jpg"))) == 3
    lines = [ln for p in (tmp_path / "labels" / "heldout").glob("*.txt") for ln in p.read_text().splitlines()]
    assert len(lines) == n_labels
    assert "names" in (tmp_path / "data.yaml").read_text()


def test_visible_fraction_is_visible_pixels_over_the_silhouette() -> None:
    """Measured on request (evaluation by visibility), the same images otherwise."""
    plain = DatasetSpec(split="heldout", n_rooms=1, images_per_room=4, intrinsics=SMALL, min_visible_px=20)
    spec = dataclasses.replace(plain, measure_visibility=True)
    fractions = []
    for a, b in zip(generate(plain), generate(spec), strict=True):
        assert a.visible_fraction is None
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.object_ids, b.object_ids)
        assert b.visible_fraction is not None and b.visible_fraction.shape == b.visible_px.shape
        assert np.all((b.visible_fraction > 0) & (b.visible_fraction <= 1))
        fractions.extend(b.visible_fraction.tolist())
    assert fractions and min(fractions) < 1.0  # furniture hides furniture, borders cut it


def test_class_weights_shift_the_rooms_class_mix_and_bad_weights_are_named() -> None:
    """Weighting a class up gives more of it; a weight of 0 leaves it out entirely."""
    def count(weights: tuple[tuple[str, float], ...]) -> dict[str, int]:
        out: dict[str, int] = {}
        for seed in range(100_000, 100_040):
            room = varied_room(seed, np.random.default_rng(seed), DatasetSpec().class_names, weights)
            for o in room.objects:
                out[o.class_name] = out.get(o.class_name, 0) + 1
        return out

    plain = count(())
    rare = count((("conference_table", 6.0), ("chair", 0.0)))
    assert "chair" not in rare and plain.get("chair", 0) > 0
    assert rare.get("conference_table", 0) > 2 * plain.get("conference_table", 0)
    with pytest.raises(SimulationError, match="class_weights"):
        varied_room(100_000, np.random.default_rng(0), DatasetSpec().class_names, (("sofa", -1.0),))
    with pytest.raises(SimulationError, match="class_weights.*'armchair'"):
        varied_room(100_000, np.random.default_rng(0), DatasetSpec().class_names, (("armchair", 1.0),))


def test_class_balanced_aiming_looks_at_rare_classes_as_often_as_chairs() -> None:
    """A room of many chairs and one sofa: plain aiming points mostly at chairs, class-balanced
    aiming at the sofa about half the time."""
    base = DatasetSpec(aim_fraction=1.0)
    only = (("chair", 8.0), ("sofa", 1.0), ("desk", 0.0), ("coffee_table", 0.0),
            ("conference_table", 0.0), ("whiteboard", 0.0))
    rooms = (varied_room(s, np.random.default_rng(s), base.class_names, only) for s in range(100_000, 100_200))
    room = next(r for r in rooms if [o.class_name for o in r.objects].count("sofa") == 1
                and [o.class_name for o in r.objects].count("chair") >= 4)
    sofa = next(o for o in room.objects if o.class_name == "sofa").centroid_m()

    def sofa_share(spec: DatasetSpec) -> float:
        r = np.random.default_rng(11)
        hits = 0
        for _ in range(200):
            T = sample_camera_pose(room, spec, r)
            d = sofa - T[:3, 3]
            hits += float(np.dot(T[:3, 2], d / np.linalg.norm(d))) > math.cos(math.radians(35.0))
        return hits / 200

    plain, balanced = sofa_share(base), sofa_share(DatasetSpec(aim_fraction=1.0, aim_class_balanced=True))
    assert balanced > 0.35 and balanced > plain + 0.15, (plain, balanced)


def test_clutter_aiming_looks_at_clutter_and_bad_fraction_is_named() -> None:
    """Hard negatives: with every aimed image aimed at clutter, the camera looks at a piece of
    clutter far more often than with plain aiming at furniture."""
    names = DatasetSpec().class_names
    room = next(r for r in (varied_room(s, np.random.default_rng(s), names) for s in range(100_000, 100_100))
                if len(r.clutter) >= 2 and len(r.objects) >= 4)
    clutter = np.array([c.centroid_m() for c in room.clutter])

    def clutter_share(spec: DatasetSpec) -> float:
        r = np.random.default_rng(5)
        hits = 0
        for _ in range(200):
            T = sample_camera_pose(room, spec, r)
            d = clutter - T[:3, 3]
            cos = (d @ T[:3, 2]) / np.linalg.norm(d, axis=1)
            hits += bool(np.any(cos > math.cos(math.radians(20.0))))
        return hits / 200

    plain = clutter_share(DatasetSpec(aim_fraction=1.0))
    aimed = clutter_share(DatasetSpec(aim_fraction=1.0, aim_clutter_fraction=1.0))
    assert aimed > 0.6 and aimed > plain + 0.25, (plain, aimed)
    with pytest.raises(SimulationError, match="aim_clutter_fraction"):
        DatasetSpec(aim_clutter_fraction=1.5)
