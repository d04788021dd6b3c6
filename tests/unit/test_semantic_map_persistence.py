"""SemanticMap: integrating frames, save/load round trip, atomic writes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import semmap.semantic_map as sm_mod
from semmap.config import default_classes
from semmap.costmap import (
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    ObjectFootprint,
    VerticalBand,
)
from semmap.errors import MapError
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform
from semmap.geometry import ObjectObservation
from semmap.objects import ObjectMap
from semmap.semantic_map import SemanticMap, SemanticMapSettings
from semmap.types import CameraIntrinsics, Frame

K = CameraIntrinsics(200.0, 200.0, 80.0, 60.0, 160, 120)
CLASSES = ("chair", "coffee_table")


def settings(**kw) -> SemanticMapSettings:  # type: ignore[no-untyped-def]
    base = dict(
        class_names=CLASSES, scan_band=VerticalBand(0.4, 0.8), origin_xy_m=(-1.0, -2.0),
        size_xy_m=(3.0, 4.0), class_margins_m=(("chair", 0.2), ("coffee_table", 0.15)),
    )
    base.update(kw)
    return SemanticMapSettings(**base)


def wall_frame(x_m: float, stamp_s: float, index: int) -> Frame:
    T = make_transform(R_BODY_CAMERA_FORWARD, np.array([x_m, 0.0, 0.6]))
    depth = np.full((K.height_px, K.width_px), 3.0, np.float32)
    rgb = np.zeros((K.height_px, K.width_px, 3), np.uint8)
    return Frame(stamp_s, rgb, depth, K, T_map_camera=T, index=index)


def built_map() -> SemanticMap:
    m = SemanticMap(settings())
    for i in range(5):
        m.integrate_frame(wall_frame(0.1 * i, 0.1 * i, i))
    table = ObjectFootprint(4, "coffee_table", np.array([[1.0, -0.5], [1.8, -0.5], [1.8, 0.0], [1.0, 0.0]]), 0.0, 0.45, 0.8)
    m.set_objects([table], 0.4, {4: np.array([0.1, 0.9])})
    return m


def test_integrate_frame_maps_the_wall_and_grows() -> None:
    m = built_map()
    assert m.spec.extent_xy_m[2] >= 3.4  # grew east to hold the wall at x = 3.0 + 0.4
    p = m.grid.probability_at_xy(np.array([[3.4, 0.0], [1.5, 0.5], [5.5, 0.0]]))
    assert p[0] > 0.5 and p[1] < 0.5 and np.isnan(p[2])
    assert len(m.path_xyz_m) == 5 and m.frames_integrated == 5
    assert m.objects[0].margin_m == 0.15  # class margin filled in
    assert m.stale_layers(0.5) == []
    assert m.stale_layers(10.0) != []
    assert m.is_fresh(0.5) and m.is_fresh(2.4) and not m.is_fresh(10.0)
    grid_only = SemanticMap(settings())
    grid_only.integrate_frame(wall_frame(0.0, 5.0, 0))
    assert grid_only.is_fresh(6.0)  # no object input: the grid alone decides
    assert not SemanticMap(settings()).is_fresh(0.0)  # never updated


def test_integrate_frame_needs_a_pose() -> None:
    m = SemanticMap(settings())
    f = wall_frame(0.0, 0.0, 0)
    bare = Frame(f.stamp_s, f.rgb, f.depth_m, K)
    with pytest.raises(MapError, match="no camera pose"):
        m.integrate_frame(bare)


def test_save_load_round_trip(tmp_path: Path) -> None:
    m = built_map()
    band = VerticalBand(0.3, 0.5)
    before = m.costmap(band)
    path = m.save(tmp_path / "state" / "map.npz")
    loaded = SemanticMap.load(path)
    assert loaded.settings == m.settings
    assert loaded.spec == m.spec
    assert np.array_equal(loaded.grid.values, m.grid.values)
    assert np.allclose(loaded.path_xyz_m, m.path_xyz_m)
    assert [o.object_id for o in loaded.objects] == [4]
    assert np.allclose(loaded.class_probabilities(4), [0.1, 0.9])
    after = loaded.costmap(band)
    assert np.array_equal(after.cost, before.cost)
    assert after.stamp_s == pytest.approx(before.stamp_s)
    assert loaded.frames_integrated == 5
    # The loaded map keeps mapping.
    loaded.integrate_frame(wall_frame(0.5, 0.5, 5))
    assert loaded.frames_integrated == 6


def test_atomic_write_leaves_no_partial_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = built_map()
    path = m.save(tmp_path / "map.npz")
    good = path.read_bytes()
    m.integrate_frame(wall_frame(0.9, 1.0, 9))

    def failing_replace(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sm_mod.os, "replace", failing_replace)
    with pytest.raises(MapError, match="could not write"):
        m.save(path)
    assert path.read_bytes() == good  # previous map intact
    assert sorted(os.listdir(tmp_path)) == ["map.npz"]  # no temp file left behind


def test_load_reports_bad_files(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="no such map file"):
        SemanticMap.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(MapError, match="not a readable map file"):
        SemanticMap.load(junk)
    partial = tmp_path / "partial.npz"
    np.savez(partial, grid_values=np.zeros((2, 2), np.uint16))
    with pytest.raises(MapError, match="missing entry 'path'"):
        SemanticMap.load(partial)


def table_observation(track_id: int, stamp_s: float) -> ObjectObservation:
    poly = np.array([[1.0, -0.5], [1.8, -0.5], [1.8, 0.0], [1.0, 0.0]])
    return ObjectObservation(
        track_id=track_id, class_name="coffee_table", score=0.9, stamp_s=stamp_s,
        centroid_map_m=(1.4, -0.25, 0.3), footprint_xy_m=poly, z_min_m=0.0, z_max_m=0.45,
        n_points=800, n_voxels=200, range_m=1.5,
    )


def test_object_map_feeds_the_layers_and_survives_a_restart(tmp_path: Path) -> None:
    classes = [c for c in default_classes() if c.name in CLASSES]
    m = SemanticMap(settings(), ObjectMap(classes))
    for i in range(4):
        m.integrate_frame(wall_frame(0.0, 0.1 * i, i), observations=[table_observation(7, 0.1 * i)])
    assert [o.class_name for o in m.objects] == ["coffee_table"]
    assert m.objects[0].margin_m == pytest.approx(0.2)  # the object map's class margin
    low = m.costmap(VerticalBand(0.3, 0.5))
    assert low.cost_at_xy(np.array([[1.4, -0.25]]))[0] == LETHAL_OBSTACLE
    high = m.costmap(VerticalBand(1.4, 1.6))
    assert high.cost_at_xy(np.array([[1.4, -0.25]]))[0] != LETHAL_OBSTACLE
    with pytest.raises(MapError, match="not both"):
        m.integrate_frame(wall_frame(0.0, 1.0, 9), objects=[], observations=[])

    path = m.save(tmp_path / "map.npz")
    saved_id = m.objects[0].object_id
    fresh = ObjectMap(classes)
    loaded = SemanticMap.load(path, object_map=fresh)
    # The object map itself is restored: the table keeps its id, and a new track over it
    # after the restart is the same table.
    assert [(o.object_id, o.class_name) for o in fresh.objects()] == [(saved_id, "coffee_table")]
    loaded.integrate_frame(wall_frame(0.0, 1.0, 10), observations=[])
    assert [o.class_name for o in loaded.objects] == ["coffee_table"]
    assert loaded.costmap(VerticalBand(0.3, 0.5)).cost_at_xy(np.array([[1.4, -0.25]]))[0] == LETHAL_OBSTACLE
    for i in range(4):
        loaded.integrate_frame(wall_frame(0.0, 1.1 + 0.1 * i, 11 + i), observations=[table_observation(3, 1.1 + 0.1 * i)])
    assert [o.object_id for o in loaded.objects] == [saved_id]


def test_a_damaged_saved_object_map_keeps_its_objects_until_seen(tmp_path: Path) -> None:
    classes = [c for c in default_classes() if c.name in CLASSES]
    m = SemanticMap(settings(), ObjectMap(classes))
    for i in range(4):
        m.integrate_frame(wall_frame(0.0, 0.1 * i, i), observations=[table_observation(7, 0.1 * i)])
    path = m.save(tmp_path / "map.npz")
    # The saved object map loses a footprint: the object map cannot take the dump and starts
    # empty, and the saved table stays in the layers until the object map sees it again.
    data = dict(np.load(path))
    meta = json.loads(data["meta"].tobytes().decode("utf-8"))
    meta["object_map"]["objects"][0].pop("footprint_xy_m")
    data["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    np.savez(tmp_path / "damaged.npz", **data)
    empty = ObjectMap(classes)
    loaded = SemanticMap.load(tmp_path / "damaged.npz", object_map=empty)
    assert len(empty) == 0
    loaded.integrate_frame(wall_frame(0.0, 1.0, 10), observations=[])
    assert [o.class_name for o in loaded.objects] == ["coffee_table"]
    assert loaded.objects[0].object_id >= sm_mod.RESTORED_ID_OFFSET
    for i in range(4):
        loaded.integrate_frame(wall_frame(0.0, 1.1 + 0.1 * i, 11 + i), observations=[table_observation(3, 1.1 + 0.1 * i)])
    assert len(loaded.objects) == 1 and loaded.objects[0].object_id < sm_mod.RESTORED_ID_OFFSET


def test_object_map_classes_must_match() -> None:
    with pytest.raises(MapError, match="classes"):
        SemanticMap(settings(), ObjectMap(default_classes()))


def test_settings_saved_with_the_old_decay_key_still_load() -> None:
    d = settings(clearance_decay_m=0.3).to_dict()
    d["margin_decay_m"] = d.pop("clearance_decay_m")
    assert SemanticMapSettings.from_dict(json.loads(json.dumps(d))).clearance_decay_m == 0.3


def _table(object_id: int, margin_m: float | None) -> ObjectFootprint:
    poly = np.array([[1.0, -0.5], [1.8, -0.5], [1.8, 0.0], [1.0, 0.0]]) + [0.0, 2.0 * object_id]
    return ObjectFootprint(object_id, "coffee_table", poly, 0.0, 0.45, 0.9, margin_m=margin_m)


def test_a_zero_margin_stays_zero_and_none_takes_the_class_margin(tmp_path: Path) -> None:
    m = SemanticMap(settings())
    m.set_objects([_table(0, 0.0), _table(1, None)], 0.4)
    assert [o.margin_m for o in m.objects] == [0.0, 0.15]
    # 0.1 m beside each table: inside the coffee table's 0.15 m keep-out only for the second.
    beside = np.array([[1.9, -0.25], [1.9, 1.75]])
    cost = m.costmap(VerticalBand(0.3, 0.5)).cost_at_xy(beside)
    assert cost[0] < INSCRIBED_INFLATED_OBSTACLE <= cost[1]
    loaded = SemanticMap.load(m.save(tmp_path / "map.npz"))
    assert [o.margin_m for o in loaded.objects] == [0.0, 0.15]
    assert np.array_equal(loaded.costmap(VerticalBand(0.3, 0.5)).cost_at_xy(beside), cost)


@pytest.mark.parametrize("saved", ["missing", None])
def test_a_saved_object_without_a_margin_loads_with_its_class_margin(tmp_path: Path, saved: str | None) -> None:
    m = SemanticMap(settings())
    m.set_objects([_table(0, 0.3)], 0.4)
    path = m.save(tmp_path / "map.npz")
    data = dict(np.load(path))
    meta = json.loads(data["meta"].tobytes().decode("utf-8"))
    if saved == "missing":
        del meta["objects"][0]["margin_m"]
    else:
        meta["objects"][0]["margin_m"] = None
    data["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    np.savez(tmp_path / "old.npz", **data)
    assert [o.margin_m for o in SemanticMap.load(tmp_path / "old.npz").objects] == [0.15]
