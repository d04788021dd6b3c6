"""Map exports: ROS map_server PGM/YAML (golden file), nav_msgs values, PNG, JSON, GeoJSON."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from semmap.costmap import LETHAL_OBSTACLE, NO_INFORMATION, ObjectFootprint, VerticalBand
from semmap.errors import MapError
from semmap.export import (
    PGM_FREE,
    PGM_OCCUPIED,
    PGM_UNKNOWN,
    cost_to_probability,
    export_all,
    geojson,
    map_to_lon_lat,
    nav_msgs_values,
    object_footprints_from_records,
    read_ros_map,
    render_picture,
    write_objects_json,
    write_ros_map,
)
from semmap.grid import GridSpec
from semmap.semantic_map import SemanticMap, SemanticMapSettings

DATA = Path(__file__).resolve().parents[1] / "data"
SPEC = GridSpec(0.05, (-1.0, -0.5), (6, 8))


def golden_probability() -> np.ndarray:
    """A small asymmetric map: unknown left column, a wall on the top row, free elsewhere,
    one uncertain cell (so a flipped or transposed file cannot pass)."""
    p = np.full(SPEC.shape_rc, 0.2, np.float32)
    p[:, 0] = np.nan
    p[5, 1:] = 0.9
    p[0, 7] = 0.5
    p[2, 3] = 0.7
    return p


def test_pgm_yaml_matches_golden_files(tmp_path: Path) -> None:
    pgm, yml = write_ros_map(tmp_path / "golden_map", golden_probability(), SPEC)
    assert pgm.read_bytes() == (DATA / "golden_map.pgm").read_bytes()
    assert yml.read_text() == (DATA / "golden_map.yaml").read_text()


def test_golden_map_loads_back_as_the_grid() -> None:
    m = read_ros_map(DATA / "golden_map.yaml")
    meta = yaml.safe_load((DATA / "golden_map.yaml").read_text())
    assert set(meta) == {"image", "mode", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    assert m.spec == SPEC
    # The PGM's first row is the top (north) of the map.
    assert m.image.shape == SPEC.shape_rc
    assert np.all(m.image[0, 1:] == PGM_OCCUPIED) and m.image[0, 0] == PGM_UNKNOWN
    assert m.image[5, 7] == PGM_UNKNOWN  # p = 0.5 is neither free nor occupied
    expected = nav_msgs_values(golden_probability())
    trinary = np.where(expected < 0, -1, np.where(expected > 50, 100, np.where(expected < 50, 0, -1)))
    assert np.array_equal(m.occupancy, trinary)
    assert m.occupancy[2, 3] == 100 and m.occupancy[3, 3] == 0


def test_opencv_reads_the_pgm_as_a_standard_image() -> None:
    img = cv2.imread(str(DATA / "golden_map.pgm"), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint8 and img.shape == SPEC.shape_rc
    assert set(np.unique(img)) <= {PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN}


def test_scale_mode_round_trip(tmp_path: Path) -> None:
    p = golden_probability()
    _, yml = write_ros_map(tmp_path / "m", p, SPEC, mode="scale")
    m = read_ros_map(yml)
    assert m.meta["mode"] == "scale"
    assert m.occupancy[0, 0] == -1 and m.occupancy[5, 3] == 100
    assert 0 <= m.occupancy[1, 3] < m.occupancy[0, 7] < 100  # p 0.2 < p 0.5, kept as scale


def test_nav_msgs_values() -> None:
    v = nav_msgs_values(np.array([[np.nan, 0.0, 0.494, 1.0]]))
    assert v.dtype == np.int8 and v.tolist() == [[-1, 0, 49, 100]]


def test_bad_inputs_are_named(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="does not match"):
        write_ros_map(tmp_path / "x", np.zeros((2, 2)), SPEC)
    with pytest.raises(MapError, match="mode"):
        write_ros_map(tmp_path / "x", golden_probability(), SPEC, mode="raw")
    (tmp_path / "bad.yaml").write_text("image: m.pgm\nresolution: 0.05\n")
    with pytest.raises(MapError, match="missing key 'origin'"):
        read_ros_map(tmp_path / "bad.yaml")


def test_cost_to_probability() -> None:
    p = cost_to_probability(np.array([0, 126, LETHAL_OBSTACLE, NO_INFORMATION], np.uint8))
    assert p[0] == 0.0 and 0.4 < p[1] < 0.6 and p[2] == 1.0 and np.isnan(p[3])


def small_map() -> SemanticMap:
    settings = SemanticMapSettings(
        ("chair", "desk"), VerticalBand(0.4, 0.8), origin_xy_m=(0.0, 0.0), size_xy_m=(4.0, 3.0),
        class_margins_m=(("chair", 0.2), ("desk", 0.25)),
    )
    sm = SemanticMap(settings)
    rows, cols = sm.spec.shape_rc
    free = np.argwhere(np.ones((rows - 10, cols - 10), bool)) + 5
    sm.grid.apply(np.array([[5, c] for c in range(5, cols - 5)]), free)
    desk = ObjectFootprint(3, "desk", np.array([[1.0, 1.0], [2.2, 1.0], [2.2, 1.6], [1.0, 1.6]]), 0.0, 0.75, 0.9)
    chair = ObjectFootprint(7, "chair", np.array([[2.8, 1.9], [3.3, 1.9], [3.3, 2.4], [2.8, 2.4]]), 0.0, 0.9, 0.7)
    sm.set_objects([desk, chair], 1.0, {7: np.array([0.8, 0.2])})
    for i, x in enumerate(np.linspace(0.5, 3.5, 8)):
        sm._record_path(float(i), np.array([x, 0.6, 0.6]))
    return sm


def test_png_picture_shows_objects_in_class_colours(tmp_path: Path) -> None:
    sm = small_map()
    colours = {"chair": (230, 25, 75), "desk": (70, 240, 240)}
    img = render_picture(sm, colours)
    assert img.ndim == 3 and img.shape[1] >= 900
    bgr_chair = np.array([75, 25, 230])
    # The chair outline colour appears in the picture.
    assert np.any(np.all(np.abs(img.astype(int) - bgr_chair) < 8, axis=2))
    files = export_all(tmp_path / "out", sm, colours, geo_origin_lat_lon_deg=(47.397742, 8.545594))
    png = cv2.imread(str(files["picture"]))
    assert png is not None and png.shape == img.shape
    for key in ("map_pgm", "map_yaml", "costmap_pgm", "costmap_yaml", "objects", "geojson", "map"):
        assert files[key].is_file(), key
    assert read_ros_map(files["costmap_yaml"]).occupancy.max() == 100


def test_objects_json_round_trip(tmp_path: Path) -> None:
    sm = small_map()
    path = write_objects_json(tmp_path / "objects.json", sm)
    doc = json.loads(path.read_text())
    assert doc["class_names"] == ["chair", "desk"]
    by_id = {o["object_id"]: o for o in doc["objects"]}
    assert by_id[7]["class_probabilities"] == {"chair": 0.8, "desk": 0.2}
    assert by_id[3]["class_probabilities"] == {"chair": 0.0, "desk": 1.0}
    assert by_id[3]["margin_m"] == 0.25 and by_id[3]["z_max_m"] == 0.75
    back = object_footprints_from_records(doc["objects"])
    assert [b.object_id for b in back] == [3, 7]
    assert np.allclose(back[0].polygon_xy_m, sm.objects[0].polygon_xy_m)
    assert [b.margin_m for b in back] == [0.25, 0.2]


def test_objects_json_without_a_margin_means_the_class_margin() -> None:
    rec = {"object_id": 1, "class_name": "desk", "existence": 0.9, "z_min_m": 0.0, "z_max_m": 0.75,
           "polygon_xy_m": [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]}
    back = object_footprints_from_records([rec, {**rec, "margin_m": None}, {**rec, "margin_m": 0.0}])
    assert [b.margin_m for b in back] == [None, None, 0.0]


def test_geojson_is_lon_lat_with_closed_rings() -> None:
    sm = small_map()
    doc = geojson(sm, 47.0, 8.0)
    assert doc["type"] == "FeatureCollection"
    polys = [f for f in doc["features"] if f["geometry"]["type"] == "Polygon"]
    assert len(polys) == 2
    ring = polys[0]["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1]
    lon, lat = ring[0]
    assert 7.99 < lon < 8.01 and 46.99 < lat < 47.01
    assert any(f["geometry"]["type"] == "LineString" for f in doc["features"])
    # 1 m east and north of the origin.
    ll = map_to_lon_lat(np.array([[1.0, 1.0]]), 47.0, 8.0)[0]
    assert (ll[1] - 47.0) * 111_319.49 == pytest.approx(1.0, rel=1e-3)
    assert (ll[0] - 8.0) * 111_319.49 * np.cos(np.radians(47.0)) == pytest.approx(1.0, rel=1e-3)
