"""The shipped models by name: ``builtin:coco`` for real cameras, ``builtin:furniture`` for the
simulator, ``auto`` choosing between them, and the side files that give a shipped model its
class names and class map."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from companion.config import CompanionConfig, load_config
from companion.service.perception_worker import PerceptionPipeline, new_semantic_map
from semmap.config import ClassConfig, DetectorConfig
from semmap.detection import BUILTIN_MODELS_DIR, detector_from_config, resolve_model_path
from semmap.detection.builtin import builtin_defaults, builtin_model_file
from semmap.detection.onnx_detector import OnnxDetector
from semmap.errors import PerceptionError

REPO = Path(__file__).resolve().parents[2]
OURS = [c.name for c in CompanionConfig().classes]
CPU = ["CPUExecutionProvider"]


def _mapped(det: OnnxDetector) -> dict[str, str]:
    """Model class name -> our class, for the model classes the detector keeps."""
    cm = det.class_map
    return {cm.model_names[i]: cm.semantic_names[int(k)] for i, k in enumerate(cm.lookup) if k >= 0}


def test_auto_is_the_coco_model_on_a_real_camera_and_the_furniture_model_in_the_simulator() -> None:
    assert CompanionConfig().detector.model_path == "auto"
    assert resolve_model_path("auto", real_camera=True) == "builtin:coco"
    assert resolve_model_path("auto", real_camera=False) == "builtin:furniture"
    for explicit in ("builtin:furniture", "/models/mine.onnx", None):
        assert resolve_model_path(explicit, real_camera=True) == explicit


def test_the_coco_model_ships_small_with_its_licence_notice_and_card() -> None:
    path = builtin_model_file(BUILTIN_MODELS_DIR, "coco")
    assert path.name == "coco_yolox_nano_416.onnx"
    assert 3_000_000 < path.stat().st_size < 4_000_000
    notice = (BUILTIN_MODELS_DIR / "NOTICE.coco_yolox_nano_416").read_text()
    assert "Megvii" in notice and "Kazuhito00/YOLOX-ONNX-TFLite-Sample" in notice
    assert "Apache License" in (BUILTIN_MODELS_DIR / "LICENSE.coco_yolox_nano_416").read_text()
    card = (BUILTIN_MODELS_DIR / "MODEL_CARD.coco.md").read_text()
    assert "whiteboard" in card and "416" in card


def test_builtin_coco_loads_with_its_class_names_and_class_map() -> None:
    det = detector_from_config(DetectorConfig(model_path="auto", providers=CPU), OURS, real_camera=True)
    assert isinstance(det, OnnxDetector)
    assert det.model_path.name == "coco_yolox_nano_416.onnx"
    assert (det.head, det.input_hw_px) == ("yolox", (416, 416))
    assert len(det.class_map.model_names) == 80
    assert _mapped(det) == {"chair": "chair", "sofa": "sofa", "diningtable": "desk"}


def test_the_simulator_keeps_the_furniture_model() -> None:
    det = detector_from_config(DetectorConfig(model_path="auto", providers=CPU), OURS, real_camera=False)
    assert isinstance(det, OnnxDetector)
    assert det.model_path.name.startswith("furniture_")


def test_the_service_on_a_realsense_runs_the_coco_model_without_detector_configuration() -> None:
    cfg = CompanionConfig.model_validate({"camera": {"source": "realsense"},
                                          "detector": {"providers": CPU}})
    pipeline = PerceptionPipeline.from_config(cfg, new_semantic_map(cfg))
    assert isinstance(pipeline.detector, OnnxDetector)
    assert pipeline.detector.model_path.name == "coco_yolox_nano_416.onnx"


def test_the_d455_example_config_names_the_coco_model() -> None:
    cfg = load_config(REPO / "config" / "hummingbird-d455.yaml")
    assert cfg.camera.source == "realsense"
    assert cfg.detector.model_path == "builtin:coco"


def test_a_deployment_adds_a_coco_class_by_configuration_alone() -> None:
    classes = [*CompanionConfig().classes,
               ClassConfig(name="bed", hollow="none", margin_m=0.2, color_rgb=(200, 200, 0))]
    names = [c.name for c in classes]
    cfg = DetectorConfig(model_path="builtin:coco", providers=CPU,
                         class_map={"chair": "chair", "sofa": "sofa", "diningtable": "desk", "bed": "bed"})
    det = detector_from_config(cfg, names)
    assert isinstance(det, OnnxDetector)
    assert _mapped(det)["bed"] == "bed"


def test_the_shipped_class_map_keeps_only_configured_classes() -> None:
    det = detector_from_config(DetectorConfig(model_path="builtin:coco", providers=CPU), ["chair", "desk"])
    assert isinstance(det, OnnxDetector)
    assert _mapped(det) == {"chair": "chair", "diningtable": "desk"}


def test_a_broken_side_file_is_an_error_naming_it(tmp_path: Path) -> None:
    model = builtin_model_file(BUILTIN_MODELS_DIR, "coco")
    shutil.copy(model, tmp_path / model.name)
    (tmp_path / "coco_yolox_nano_416.classmap.json").write_text(json.dumps({"map": {}}))
    with pytest.raises(PerceptionError, match="classmap.json"):
        builtin_defaults(tmp_path / model.name)
    with pytest.raises(PerceptionError, match="classmap.json"):
        detector_from_config(DetectorConfig(model_path="builtin:coco", providers=CPU), OURS,
                             builtin_dir=tmp_path)


def test_a_model_without_side_files_reads_its_metadata() -> None:
    d = builtin_defaults(BUILTIN_MODELS_DIR / "does_not_exist.onnx")
    assert d.class_names is None and d.class_map == {}


def test_the_coco_model_runs_on_a_real_frame_and_finds_the_dining_room_furniture(real_data: Path) -> None:
    """A real colour frame of the dining room (tests/data/real): the COCO model must find
    chairs and the dining table in it, through our runtime."""
    import cv2

    rgb = cv2.cvtColor(cv2.imread(str(real_data / "rgbd" / "diningroom" / "color" / "1.png")), cv2.COLOR_BGR2RGB)
    det = detector_from_config(DetectorConfig(model_path="builtin:coco", providers=CPU), OURS)
    assert isinstance(det, OnnxDetector)
    dets = det.detect(rgb)
    classes = [d.class_name for d in dets]
    assert classes.count("chair") >= 3
    table = [d for d in dets if d.class_name == "desk"]
    assert table, classes
    # The dining table's box (labelled by hand, tests/data/real_furniture_labels.json).
    u0, v0, u1, v1 = table[0].xyxy_px
    assert np.allclose((u0, v0, u1, v1), (185, 190, 640, 478), atol=40)
