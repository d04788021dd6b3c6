"""ONNX detector: tiny ONNX graphs that emit known boxes in each head layout.

Each graph ignores its image (output = constant + 0 * mean(image)), so the decoded boxes are
known exactly and any error in letterbox inversion, decoding, thresholds, class mapping or
NMS shows up as a wrong number.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from semmap.config import DetectorConfig
from semmap.detection.decode import anchor_count, recognise_head
from semmap.detection.onnx_detector import OnnxDetector, select_providers
from semmap.errors import PerceptionError

OURS = ["chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk"]
COCO6 = ["person", "chair", "couch", "dining table", "tv", "cup"]
INPUT = 320
N_ANCHORS = anchor_count((INPUT, INPUT))  # 2100


def constant_model(path: Path, out: np.ndarray, names: list[str] | None = None,
                   input_hw: tuple[int | str, int | str] = (INPUT, INPUT)) -> Path:
    """Write an ONNX model whose output is ``out`` (batch 1) for any image."""
    x = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, *input_hw])
    y = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Add", ["z", "const"], ["output0"]),
    ]
    inits = [numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
             numpy_helper.from_array(out.astype(np.float32), "const")]
    graph = helper.make_graph(nodes, "const_head", [x], [y], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if names is not None:
        helper.set_model_props(model, {"names": str(dict(enumerate(names)))})
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def yolov8_output(boxes_cxcywh: list[tuple[float, float, float, float]],
                  scores: list[dict[int, float]], n_classes: int) -> np.ndarray:
    """(1, 4 + C, N): the given boxes at anchors 0.., every other anchor empty."""
    out = np.zeros((1, 4 + n_classes, N_ANCHORS), np.float32)
    out[0, 2:4, :] = 10.0
    for k, (b, sc) in enumerate(zip(boxes_cxcywh, scores, strict=True)):
        out[0, :4, 100 + 7 * k] = b
        for c, s in sc.items():
            out[0, 4 + c, 100 + 7 * k] = s
    return out


def yolox_raw_output(boxes_cxcywh: list[tuple[float, float, float, float]],
                     obj_cls: list[tuple[float, dict[int, float]]], n_classes: int,
                     predecoded: bool = False) -> np.ndarray:
    """(1, N, 5 + C) in YOLOX's exporter layout; each box is put on the stride-8/16/32 anchor
    whose cell holds its centre (grid-relative, log-size) unless ``predecoded``."""
    out = np.zeros((1, N_ANCHORS, 5 + n_classes), np.float32)
    for (cx, cy, w, h), (obj, cls) in zip(boxes_cxcywh, obj_cls, strict=True):
        offset = 0
        stride = 8 if w < 64 else 16 if w < 128 else 32
        for s in (8, 16, 32):
            if s == stride:
                break
            offset += (INPUT // s) ** 2
        gx, gy = int(cx // stride), int(cy // stride)
        k = offset + gy * (INPUT // stride) + gx
        if predecoded:
            out[0, k, :4] = (cx, cy, w, h)
        else:
            out[0, k, :4] = (cx / stride - gx, cy / stride - gy, math.log(w / stride), math.log(h / stride))
        out[0, k, 4] = obj
        for c, s in cls.items():
            out[0, k, 5 + c] = s
    return out


def image(w: int = 640, h: int = 480) -> np.ndarray:
    return np.full((h, w, 3), 90, np.uint8)


def boxes_of(dets):
    return {d.class_name: d.xyxy_px for d in dets}


# --- YOLOv8 ------------------------------------------------------------------------------

def test_yolov8_boxes_come_back_in_original_pixels(tmp_path: Path) -> None:
    # 640x480 -> 320x240 centred in 320x320: scale 0.5, 40 px padding on top.
    out = yolov8_output([(150.0, 160.0, 100.0, 40.0), (60.0, 100.0, 20.0, 30.0)],
                        [{0: 0.9}, {5: 0.7}], 6)
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out, OURS), OURS)
    assert det.head == "yolov8"
    dets = det.detect(image())
    assert [d.class_name for d in dets] == ["chair", "desk"]  # best score first
    np.testing.assert_allclose(dets[0].xyxy_px, (200.0, 200.0, 400.0, 280.0), atol=1e-4)
    np.testing.assert_allclose(dets[1].xyxy_px, (100.0, 90.0, 140.0, 150.0), atol=1e-4)
    assert dets[0].score == pytest.approx(0.9)
    assert dets[1].score == pytest.approx(0.7)


def test_yolov8_boxes_are_clipped_to_the_image(tmp_path: Path) -> None:
    out = yolov8_output([(10.0, 60.0, 40.0, 60.0)], [{0: 0.8}], 6)
    dets = OnnxDetector(constant_model(tmp_path / "m.onnx", out, OURS), OURS).detect(image())
    np.testing.assert_allclose(dets[0].xyxy_px, (0.0, 0.0, 60.0, 100.0), atol=1e-4)


def test_coco_class_map_translates_and_ignores(tmp_path: Path) -> None:
    # Anchor 0: person 0.95 and chair 0.6 -> a chair (person is not ours and must not shadow).
    # Anchor 1: couch -> sofa. Anchor 2: dining table -> desk. Anchor 3: tv only -> dropped.
    out = yolov8_output(
        [(100, 100, 40, 40), (200, 200, 60, 40), (250, 120, 50, 30), (40, 250, 20, 20)],
        [{0: 0.95, 1: 0.6}, {2: 0.8}, {3: 0.7}, {4: 0.99}], 6,
    )
    cfg = DetectorConfig(kind="onnx", model_path=str(constant_model(tmp_path / "coco.onnx", out, COCO6)),
                         class_map={"chair": "chair", "couch": "sofa", "dining table": "desk"},
                         providers=["CPUExecutionProvider"])
    det = OnnxDetector.from_config(cfg, OURS)
    dets = det.detect(image())
    assert sorted(d.class_name for d in dets) == ["chair", "desk", "sofa"]
    chair = next(d for d in dets if d.class_name == "chair")
    assert chair.score == pytest.approx(0.6)


def test_class_map_by_index_when_model_has_no_names(tmp_path: Path) -> None:
    out = yolov8_output([(100, 100, 40, 40)], [{2: 0.8}], 6)
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out), OURS, class_map={"2": "sofa"})
    assert [d.class_name for d in det.detect(image())] == ["sofa"]


def test_per_class_score_thresholds(tmp_path: Path) -> None:
    out = yolov8_output([(100, 100, 40, 40), (200, 200, 40, 40)], [{0: 0.7}, {5: 0.3}], 6)
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out, OURS), OURS,
                       score_threshold=0.25, class_score_thresholds={"chair": 0.8})
    assert [d.class_name for d in det.detect(image())] == ["desk"]


def test_nms_is_class_aware(tmp_path: Path) -> None:
    # Two chairs nearly on top of each other -> one; a desk on the same spot survives.
    out = yolov8_output(
        [(100, 100, 60, 60), (102, 101, 60, 60), (101, 100, 60, 60)],
        [{0: 0.9}, {0: 0.8}, {5: 0.6}], 6,
    )
    dets = OnnxDetector(constant_model(tmp_path / "m.onnx", out, OURS), OURS, nms_iou=0.5).detect(image())
    assert [(d.class_name, round(d.score, 2)) for d in dets] == [("chair", 0.9), ("desk", 0.6)]


def test_max_detections_keeps_the_best(tmp_path: Path) -> None:
    boxes = [(20.0 + 30 * i, 100.0, 20.0, 20.0) for i in range(8)]
    out = yolov8_output(boxes, [{0: 0.3 + 0.05 * i} for i in range(8)], 6)
    dets = OnnxDetector(constant_model(tmp_path / "m.onnx", out, OURS), OURS, max_detections=3).detect(image())
    assert [round(d.score, 2) for d in dets] == [0.65, 0.6, 0.55]


# --- YOLOX -------------------------------------------------------------------------------

@pytest.mark.parametrize("predecoded", [False, True])
def test_yolox_grid_decoding(tmp_path: Path, predecoded: bool) -> None:
    # YOLOX letterbox: 640x480 -> 320x240 in the top-left corner, no offset.
    boxes = [(100.0, 60.0, 40.0, 30.0), (200.0, 150.0, 100.0, 80.0), (160.0, 120.0, 200.0, 150.0)]
    oc = [(0.9, {0: 0.9}), (0.8, {3: 1.0}), (0.9, {1: 0.5})]
    out = yolox_raw_output(boxes, oc, 6, predecoded=predecoded)
    det = OnnxDetector(constant_model(tmp_path / "x.onnx", out), OURS, head="yolox",
                       class_map={"0": "chair", "3": "sofa", "1": "desk"}, yolox_predecoded=predecoded)
    got = boxes_of(det.detect(image()))
    np.testing.assert_allclose(got["chair"], (160.0, 90.0, 240.0, 150.0), atol=1e-3)
    np.testing.assert_allclose(got["sofa"], (300.0, 220.0, 500.0, 380.0), atol=1e-3)
    np.testing.assert_allclose(got["desk"], (120.0, 90.0, 520.0, 390.0), atol=1e-3)


def test_yolox_score_is_objectness_times_class(tmp_path: Path) -> None:
    out = yolox_raw_output([(100.0, 60.0, 40.0, 30.0), (200.0, 200.0, 40.0, 30.0)],
                           [(0.5, {0: 0.8}), (0.2, {0: 0.99})], 6)
    det = OnnxDetector(constant_model(tmp_path / "x.onnx", out, OURS), OURS, score_threshold=0.25)
    assert det.head == "yolox"  # recognised from the shape
    dets = det.detect(image())
    assert len(dets) == 1 and dets[0].score == pytest.approx(0.4)


def test_recognise_head_from_shape() -> None:
    assert recognise_head((1, 10, 2100), (320, 320), None) == ("yolov8", 6)
    assert recognise_head((1, 2100, 11), (320, 320), None) == ("yolox", 6)
    assert recognise_head((1, 84, 8400), (640, 640), 80) == ("yolov8", 80)
    with pytest.raises(PerceptionError, match="matches neither head"):
        recognise_head((1, 10, 999), (320, 320), None)
    with pytest.raises(PerceptionError, match="expected"):
        recognise_head((2100, 10), (320, 320), None)


# --- start-up errors ---------------------------------------------------------------------

def test_missing_model_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(PerceptionError, match="file not found"):
        OnnxDetector(tmp_path / "nope.onnx", OURS)


def test_malformed_model_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x00not a protobuf at all" * 10)
    with pytest.raises(PerceptionError, match=r"bad\.onnx: ONNX Runtime cannot load it"):
        OnnxDetector(bad, OURS)


def test_unknown_output_layout_fails_at_start_up(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "odd.onnx", np.zeros((1, 7, 100), np.float32), OURS)
    with pytest.raises(PerceptionError, match="matches neither head"):
        OnnxDetector(path, OURS)


def test_configured_head_must_match_the_output(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "v8.onnx", yolov8_output([], [], 6), OURS)
    with pytest.raises(PerceptionError, match="'yolox'"):
        OnnxDetector(path, OURS, head="yolox")


def test_class_map_typo_is_reported(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "coco.onnx", yolov8_output([], [], 6), COCO6)
    with pytest.raises(PerceptionError, match="'dinning table'"):
        OnnxDetector(path, OURS, class_map={"dinning table": "desk"})
    with pytest.raises(PerceptionError, match="not a semantic class"):
        OnnxDetector(path, OURS, class_map={"chair": "stool"})


def test_model_without_our_classes_and_no_map_is_rejected(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "m.onnx", yolov8_output([], [], 3), ["a", "b", "c"])
    with pytest.raises(PerceptionError, match="set detector.class_map"):
        OnnxDetector(path, OURS)


def test_no_available_provider_is_a_clear_error() -> None:
    with pytest.raises(PerceptionError, match="TensorrtExecutionProvider"):
        select_providers(["TensorrtExecutionProvider"], available=["CPUExecutionProvider"])
    assert select_providers(
        ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"],
        available=["CUDAExecutionProvider", "CPUExecutionProvider"],
    ) == ["CUDAExecutionProvider", "CPUExecutionProvider"]


def test_builtin_model_path_needs_a_folder(tmp_path: Path) -> None:
    cfg = DetectorConfig(kind="onnx", model_path="builtin:furniture")
    with pytest.raises(PerceptionError, match="no built-in model folder"):
        OnnxDetector.from_config(cfg, OURS)
    constant_model(tmp_path / "furniture.onnx", yolov8_output([(100, 100, 40, 40)], [{0: 0.9}], 6), OURS)
    det = OnnxDetector.from_config(cfg.model_copy(update={"providers": ["CPUExecutionProvider"]}),
                                   OURS, builtin_dir=tmp_path)
    assert len(det.detect(image())) == 1


def test_dynamic_input_size_uses_the_configured_size(tmp_path: Path) -> None:
    out = np.zeros((1, 10, anchor_count((256, 256))), np.float32)
    out[0, 2:4] = 10.0
    out[0, :4, 0] = (128, 128, 64, 64)
    out[0, 4, 0] = 0.9
    path = constant_model(tmp_path / "dyn.onnx", out, OURS, input_hw=("height", "width"))
    det = OnnxDetector(path, OURS, input_size_px=256)
    assert det.input_hw_px == (256, 256)
    # 512x512 image: scale 0.5, no padding.
    dets = det.detect(np.zeros((512, 512, 3), np.uint8))
    np.testing.assert_allclose(dets[0].xyxy_px, (192.0, 192.0, 320.0, 320.0), atol=1e-4)


def test_detector_from_config_builds_either_kind(tmp_path: Path) -> None:
    from semmap.detection import detector_from_config
    from semmap.detection.oracle import OracleDetector
    from semmap.types import CameraIntrinsics, Frame

    path = constant_model(tmp_path / "m.onnx", yolov8_output([(150.0, 160.0, 100.0, 40.0)], [{0: 0.9}], 6), OURS)
    onnx_det = detector_from_config(
        DetectorConfig(kind="onnx", model_path=str(path), providers=["CPUExecutionProvider"]), OURS)
    f = Frame(0.0, image(), np.zeros((480, 640), np.float32), CameraIntrinsics(383, 383, 320, 240, 640, 480))
    assert [d.class_name for d in onnx_det.detect_frame(f)] == ["chair"]
    assert isinstance(detector_from_config(DetectorConfig(kind="oracle"), OURS), OracleDetector)
    with pytest.raises(PerceptionError, match="model_path is not set"):
        detector_from_config(DetectorConfig(kind="onnx", model_path=None), OURS)


def test_fp16_model_gets_a_half_precision_input(tmp_path: Path) -> None:
    x = helper.make_tensor_value_info("images", TensorProto.FLOAT16, [1, 3, INPUT, INPUT])
    out = yolov8_output([(150.0, 160.0, 100.0, 40.0)], [{0: 0.9}], 6)
    y = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))
    nodes = [helper.make_node("ReduceMean", ["images"], ["m16"], keepdims=0),
             helper.make_node("Cast", ["m16"], ["m"], to=TensorProto.FLOAT),
             helper.make_node("Mul", ["m", "zero"], ["z"]),
             helper.make_node("Add", ["z", "const"], ["output0"])]
    inits = [numpy_helper.from_array(np.array(0.0, np.float32), "zero"), numpy_helper.from_array(out, "const")]
    model = helper.make_model(helper.make_graph(nodes, "fp16", [x], [y], inits),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "h.onnx"))
    dets = OnnxDetector(tmp_path / "h.onnx", OURS, model_class_names=OURS).detect(image())
    np.testing.assert_allclose(dets[0].xyxy_px, (200.0, 200.0, 400.0, 280.0), atol=1e-3)


def test_tensorrt_gets_engine_cache_and_precision_options() -> None:
    from semmap.detection.onnx_detector import _provider_entries

    entries = _provider_entries(["TensorrtExecutionProvider", "CPUExecutionProvider"], True, "/var/cache/trt")
    assert entries[1] == "CPUExecutionProvider"
    name, opts = entries[0]
    assert name == "TensorrtExecutionProvider"
    assert opts == {"trt_fp16_enable": True, "trt_engine_cache_enable": True,
                    "trt_engine_cache_path": "/var/cache/trt"}
    assert _provider_entries(["TensorrtExecutionProvider"], False, None) == [
        ("TensorrtExecutionProvider", {"trt_fp16_enable": False})]
