"""``companion map`` on the real dining-room recording with its detections file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import load_config
from companion.offline_map import OfflineMapOptions, build_offline_map, load_detections_file
from semmap.errors import ConfigError, DataError
from semmap.export import read_ros_map
from semmap.semantic_map import SemanticMap


@pytest.fixture(scope="module")
def dining(real_data: Path) -> Path:
    return real_data / "rgbd" / "diningroom"


def test_cli_builds_and_exports_the_dining_room(dining: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "map"
    rc = main(["map", str(dining), "--out", str(out), "--detections", str(dining / "detections_yolox_nano.json"),
               "--no-tracker", "--geo-origin", "47.397742,8.545594"])
    assert rc == 0
    captured = capsys.readouterr()
    assert "mapping [" in captured.err and "5/5" in captured.err  # progress bar on stderr
    assert "5 frames" in captured.out
    for name in ("map.pgm", "map.yaml", "costmap.pgm", "costmap.yaml", "map.png", "objects.json",
                 "objects.geojson", "semantic_map.npz", "effective-config.yaml"):
        assert (out / name).is_file(), name
    ros = read_ros_map(out / "map.yaml")
    assert (ros.occupancy == 100).sum() > 50 and (ros.occupancy == 0).sum() > 1000
    doc = json.loads((out / "objects.json").read_text())
    chairs = [o for o in doc["objects"] if o["class_name"] == "chair"]
    assert len(chairs) >= 2
    # Heights above the estimated floor are chair-like (the map frame is gravity-aligned).
    for c in chairs:
        assert c["z_min_m"] < c["z_max_m"] and 0.5 < c["z_max_m"] < 1.4
    loaded = SemanticMap.load(out / "semantic_map.npz")
    assert len(loaded.objects) == len(doc["objects"])
    # The cameras fly at a plausible handheld height above the estimated floor.
    assert np.all((loaded.path_xyz_m[:, 2] > 0.5) & (loaded.path_xyz_m[:, 2] < 2.5))


def test_bad_inputs_are_reported(dining: Path, tmp_path: Path) -> None:
    cfg = load_config(None)
    oracle = cfg.model_copy(update={"detector": cfg.detector.model_copy(update={"kind": "oracle"})})
    with pytest.raises(ConfigError, match="oracle"):
        build_offline_map(dining, tmp_path / "a", oracle, OfflineMapOptions())
    with pytest.raises(DataError, match="not found"):
        build_offline_map(tmp_path / "missing", tmp_path / "b", cfg, OfflineMapOptions(detections_path=dining / "x.json"))
    bad = tmp_path / "dets.json"
    bad.write_text(json.dumps({"frames": {"1.png": [{"class": "chair", "score": 0.9, "xyxy": [5, 5, 1, 1]}]}}))
    with pytest.raises(DataError, match=r"frames\['1.png'\]\[0\]"):
        load_detections_file(bad, ["chair"])
    assert main(["map", str(dining), "--out", str(tmp_path / "c"), "--detections", str(bad)]) == 2


def test_the_shipped_detector_maps_a_recording(dining: Path, tmp_path: Path) -> None:
    """``detector.kind: onnx`` with ``builtin:furniture`` resolves the model shipped in
    semmap and runs the neural-network path over real frames (no detections file)."""
    base = load_config(None)
    cfg = base.model_copy(update={"detector": base.detector.model_copy(
        update={"kind": "onnx", "model_path": "builtin:furniture"})})
    out = tmp_path / "nn"
    result = build_offline_map(dining, out, cfg, OfflineMapOptions(use_tracker=True))
    assert (out / "map.yaml").is_file() and (out / "objects.json").is_file()
    assert result.frames_used == 5 and result.frames_skipped == 0


def test_a_recording_is_mapped_with_the_coco_model_by_default(dining: Path, tmp_path: Path) -> None:
    """No detector configured and no detections file: a recording is a real camera, so the
    default ``model_path: auto`` runs ``builtin:coco``, which finds the dining-room chairs."""
    result = build_offline_map(dining, tmp_path / "coco", load_config(None), OfflineMapOptions(use_tracker=False))
    cfg_used = (tmp_path / "coco" / "effective-config.yaml").read_text()
    assert "model_path: auto" in cfg_used
    confirmed = result.object_map.objects(confirmed_only=True)
    assert len([o for o in confirmed if o.class_name == "chair"]) >= 2
    # No phantom up at the ceiling fan (the furniture model's): everything stands below 1.6 m.
    assert all(o.z_max_m < 1.6 for o in confirmed)
