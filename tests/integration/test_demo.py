"""``companion demo``: the command runs end to end on a small config and writes its outputs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest
import yaml

from companion.cli import main
from companion.config import load_config

#: A closed-loop flight: the full suite runs it, `make check` does not.
pytestmark = pytest.mark.slow

pytest.importorskip("open3d")

SMALL = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 5},
}


def test_demo_command_writes_pictures_config_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_path = tmp_path / "small.yaml"
    cfg_path.write_text(yaml.safe_dump(SMALL))
    out = tmp_path / "out"
    rc = main(["demo", "--scripted", "--out", str(out), "--config", str(cfg_path), "--frames", "6", "--pictures", "2"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "ground_truth_map" in printed

    summary = json.loads((out / "summary.json").read_text())
    assert summary["seed"] == 3 and summary["frames"]["rendered"] == 6
    assert len(summary["objects"]) == 5
    assert summary["flight"]["min_clearance_m"] >= 0.3
    assert summary["ground_truth_map"]["semantic_lethal_cells"] > summary["ground_truth_map"]["metric_lethal_cells"]
    for rel in summary["files"].values():
        assert (out / rel).is_file(), rel

    # The effective config is the one that ran, and loads back.
    assert load_config(out / "effective-config.yaml").sim.room_width_m == 6.0
    frames = sorted((out / "frames").glob("*_rgb.png"))
    assert len(frames) == 2
    img = cv2.imread(str(frames[0]))
    assert img.shape == (120, 160, 3)
    for kind in ("depth", "masks"):
        assert len(list((out / "frames").glob(f"*_{kind}.png"))) == 2
    gt = cv2.imread(str(out / "ground_truth_map.png"))
    assert gt is not None and gt.shape[1] > 2 * gt.shape[0] * 0.8  # two map panels side by side


def test_demo_seed_override_changes_the_room(tmp_path: Path) -> None:
    cfg_path = tmp_path / "small.yaml"
    cfg_path.write_text(yaml.safe_dump(SMALL))
    rooms = []
    for seed in (1, 2):
        out = tmp_path / f"seed{seed}"
        assert main(["demo", "--scripted", "--out", str(out), "--config", str(cfg_path), "--seed", str(seed),
                     "--frames", "2", "--pictures", "1"]) == 0
        rooms.append(json.loads((out / "summary.json").read_text()))
    assert rooms[0]["seed"] == 1 and rooms[1]["seed"] == 2
    assert rooms[0]["objects"] != rooms[1]["objects"]


def test_demo_with_a_bad_config_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim: {room_width_m: 1.0}\n")
    assert main(["demo", "--scripted", "--out", str(tmp_path / "o"), "--config", str(bad)]) == 2
    assert "sim.room_width_m" in capsys.readouterr().err


def test_demo_detector_choice_defaults_to_the_shipped_model_and_names_a_bad_one(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from companion.cli.demo import choose_detector
    from semmap.errors import PerceptionError

    cfg = load_config(None)
    chosen = choose_detector(cfg, "onnx")
    assert (chosen.detector.kind, chosen.detector.model_path) == ("onnx", "builtin:furniture")
    assert choose_detector(cfg, "oracle").detector.kind == "oracle"
    missing = cfg.model_copy(update={"detector": cfg.detector.model_copy(
        update={"model_path": str(tmp_path / "mine.onnx")})})
    with pytest.raises(PerceptionError, match=r"mine\.onnx: file not found"):
        choose_detector(missing, "onnx")
    assert choose_detector(missing, "auto").detector.kind == "oracle"
    assert "mine.onnx" in caplog.text and "oracle" in caplog.text
