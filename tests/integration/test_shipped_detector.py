"""The detector shipped in the package: it loads by ``builtin:furniture``, runs through our
runtime, and finds the furniture in rendered frames of rooms it was not trained on."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.sim.dataset import DatasetSpec, generate
from semmap.config import DetectorConfig
from semmap.detection import BUILTIN_MODELS_DIR, detector_from_config
from semmap.detection.onnx_detector import OnnxDetector, builtin_model_file

pytest.importorskip("open3d")

CLASSES = [c.name for c in CompanionConfig().classes]
#: Objects at least this big (visible pixels at 640x480) must be found.
BIG_PX = 2000
#: Recall over the big objects of the frames below, at IoU 0.5 with the right class (the
#: held-out benchmark, bench/detector.py, measures the model properly; this catches a model
#: that does not load, runs on the wrong colour order or scale, or has lost its class names).
MIN_RECALL = 0.6
#: The shipped file's name: architecture and input size, one of the two that suit the Jetson.
SHIPPED_NAME = re.compile(r"furniture_yolov8n_(320|416)\.onnx")


@pytest.fixture(scope="module")
def detector() -> OnnxDetector:
    cfg = DetectorConfig(kind="onnx", model_path="builtin:furniture", providers=["CPUExecutionProvider"])
    det = detector_from_config(cfg, CLASSES)
    assert isinstance(det, OnnxDetector)
    return det


def test_the_model_ships_in_the_package_with_its_card() -> None:
    path = builtin_model_file(BUILTIN_MODELS_DIR, "furniture")
    assert SHIPPED_NAME.fullmatch(path.name), path.name
    assert path.is_file() and path.stat().st_size <= 15 * 1024 * 1024
    card = (BUILTIN_MODELS_DIR / "MODEL_CARD.md").read_text()
    for name in CLASSES:
        assert name in card


def test_builtin_name_resolves_to_the_single_variant_or_the_exact_file(tmp_path: Path) -> None:
    assert builtin_model_file(tmp_path, "chairs") == tmp_path / "chairs.onnx"
    (tmp_path / "chairs_yolov8s_640.onnx").write_bytes(b"")
    assert builtin_model_file(tmp_path, "chairs") == tmp_path / "chairs_yolov8s_640.onnx"
    (tmp_path / "chairs.onnx").write_bytes(b"")
    assert builtin_model_file(tmp_path, "chairs") == tmp_path / "chairs.onnx"


def test_the_model_reports_our_classes_at_the_input_size_its_file_names(detector: OnnxDetector) -> None:
    """The file name says the input size; the network must take that size, or the model card
    and the latency figures describe another model."""
    name = SHIPPED_NAME.fullmatch(builtin_model_file(BUILTIN_MODELS_DIR, "furniture").name)
    assert name is not None
    size_px = int(name.group(1))
    assert detector.head == "yolov8"
    assert detector.input_hw_px == (size_px, size_px)
    assert detector.class_map.model_names == CLASSES
    assert bool(detector.class_map.wanted_mask.all())


def test_finds_the_furniture_in_rendered_frames_of_unseen_rooms(detector: OnnxDetector) -> None:
    # The rooms the model was trained on (scattered); on realistic rooms it is known to fall
    # short (bench/detector.py --world realistic) until it is retrained on them.
    spec = DatasetSpec(split="heldout", n_rooms=2, images_per_room=3, seed=7, class_names=tuple(CLASSES),
                       aim_fraction=1.0, motion_blur_fraction=0.0, layout="scattered")
    found = total = 0
    false_classes = 0
    for item in generate(spec):
        dets = detector.detect(item.rgb)
        assert all(d.class_name in CLASSES and 0.0 <= d.score <= 1.0 for d in dets)
        big = item.visible_px >= BIG_PX
        for box, cls in zip(item.boxes_xyxy_px[big], item.class_ids[big], strict=True):
            total += 1
            ious = [(_iou(box, np.asarray(d.xyxy_px)), d.class_name) for d in dets]
            if any(iou >= 0.5 and name == CLASSES[cls] for iou, name in ious):
                found += 1
            elif any(iou >= 0.5 for iou, _ in ious):
                false_classes += 1
    assert total >= 5, "the test's poses should see several big objects"
    assert found / total >= MIN_RECALL, f"found {found}/{total} big objects ({false_classes} with a wrong class)"


def test_an_empty_wall_gives_few_detections(detector: OnnxDetector) -> None:
    # A featureless light frame is also what a whiteboard filling the view looks like, and the
    # shipped model (0.856 mAP) says so with confidence (0.86): it may offer that one
    # full-view whiteboard (cut by every border: no object to localise, the geometry stage
    # finds a wall plane), never an object of another class, a box inside the view or several
    # boxes. Training on blank close-up walls as negatives would let this test ask for nothing.
    grey = np.full((480, 640, 3), 205, np.uint8)
    dets = detector.detect(grey)
    assert len(dets) <= 1
    for d in dets:
        u0, v0, u1, v1 = d.xyxy_px
        assert d.class_name == "whiteboard"
        assert (u1 - u0) * (v1 - v0) >= 0.9 * 640 * 480, d.xyxy_px


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    tl, br = np.maximum(a[:2], b[:2]), np.minimum(a[2:], b[2:])
    inter = float(np.prod(np.clip(br - tl, 0.0, None)))
    union = float(np.prod(a[2:] - a[:2]) + np.prod(b[2:] - b[:2])) - inter
    return inter / max(union, 1e-9)
