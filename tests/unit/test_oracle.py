"""The simulator's oracle detector on hand-made instance masks."""

from __future__ import annotations

import numpy as np
import pytest

from semmap.config import DetectorConfig
from semmap.detection.oracle import OracleDetector
from semmap.errors import FrameError
from semmap.types import CameraIntrinsics, Frame

CLASSES = ["chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk"]
INTR = CameraIntrinsics(383.0, 383.0, 320.0, 240.0, 640, 480)


def frame(objects: dict[int, tuple[int, tuple[int, int, int, int]]], with_class: bool = True) -> Frame:
    """Objects: id -> (class index, (u0, v0, u1, v1)) painted in order (later ones occlude)."""
    inst = np.zeros((480, 640), np.int32)
    cls = np.full((480, 640), -1, np.int16)
    for oid, (ci, (u0, v0, u1, v1)) in objects.items():
        inst[v0:v1, u0:u1] = oid
        cls[v0:v1, u0:u1] = ci
    masks = {"instance": inst, "class": cls} if with_class else {"instance": inst}
    return Frame(0.0, np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640), np.float32), INTR,
                 masks=masks)


def exact(**kw) -> OracleDetector:
    kw.setdefault("box_noise_px", 0.0)
    kw.setdefault("miss_rate", 0.0)
    kw.setdefault("false_positive_rate", 0.0)
    kw.setdefault("min_visible_px", 100)
    return OracleDetector(CLASSES, **kw)


def test_boxes_are_the_visible_pixels_bounding_boxes() -> None:
    f = frame({3: (0, (100, 200, 180, 330)), 7: (5, (300, 150, 500, 260))})
    dets = {d.class_name: d for d in exact().detect_frame(f)}
    assert dets["chair"].xyxy_px == (100.0, 200.0, 180.0, 330.0)
    assert dets["desk"].xyxy_px == (300.0, 150.0, 500.0, 260.0)


def test_occlusion_shrinks_the_box_and_lowers_the_score() -> None:
    # A chair 3 partly hidden behind a sofa 4 painted after it.
    f = frame({3: (0, (100, 200, 300, 400)), 4: (3, (180, 150, 400, 420))})
    gt = exact().ground_truth_boxes(f)
    assert gt[3][0] == (100.0, 200.0, 180.0, 400.0)
    scores = {"small": [], "large": []}
    for seed in range(30):
        o = exact(seed=seed)
        small = o.detect_frame(frame({1: (0, (100, 100, 125, 125))}))  # 625 px
        large = o.detect_frame(frame({1: (0, (100, 100, 300, 300))}))  # 40 000 px
        scores["small"].append(small[0].score)
        scores["large"].append(large[0].score)
    assert np.mean(scores["small"]) < np.mean(scores["large"]) - 0.1
    assert all(0.0 < s < 1.0 for v in scores.values() for s in v)
    assert 0.8 < np.mean(scores["large"]) < 0.97


def test_truncated_objects_score_lower() -> None:
    inside = [exact(seed=s).detect_frame(frame({1: (0, (200, 100, 400, 300))}))[0].score for s in range(20)]
    cut = [exact(seed=s).detect_frame(frame({1: (0, (0, 100, 200, 300))}))[0].score for s in range(20)]
    assert np.mean(cut) < np.mean(inside) - 0.1


def test_small_objects_are_not_seen() -> None:
    f = frame({1: (0, (10, 10, 19, 19)), 2: (5, (200, 200, 300, 300))})  # 81 px < 100
    assert [d.class_name for d in exact().detect_frame(f)] == ["desk"]


def test_class_from_caller_mapping_when_no_class_mask() -> None:
    f = frame({5: (0, (100, 100, 200, 200))}, with_class=False)
    assert [d.class_name for d in exact(object_classes={5: "sofa"}).detect_frame(f)] == ["sofa"]
    assert exact(object_classes={9: "sofa"}).detect_frame(f) == []  # unknown object: not a class of ours
    with pytest.raises(FrameError, match="class"):
        exact().detect_frame(f)


def test_missing_instance_mask_is_a_frame_error() -> None:
    f = Frame(0.0, np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640), np.float32), INTR)
    with pytest.raises(FrameError, match="instance"):
        exact().detect_frame(f)


def test_noise_misses_and_false_positives_are_seeded_and_at_the_configured_rates() -> None:
    f = frame({1: (0, (100, 100, 200, 250)), 2: (5, (300, 120, 520, 300))})
    cfg = DetectorConfig(oracle_box_noise_px=4.0, oracle_miss_rate=0.2,
                         oracle_false_positive_rate=0.3, oracle_min_visible_px=100)
    runs = []
    for _ in range(2):
        o = OracleDetector.from_config(cfg, CLASSES, seed=42)
        runs.append([o.detect_frame(f) for _ in range(300)])
    assert runs[0] == runs[1]  # same seed, same detections
    dets = runs[0]
    n_true = sum(1 for ds in dets for d in ds if d.class_name in ("chair", "desk")
                 and abs(d.xyxy_px[0] - (100 if d.class_name == "chair" else 300)) < 20)
    assert n_true / 600 == pytest.approx(0.8, abs=0.06)
    n_fp = sum(len(ds) for ds in dets) - n_true
    assert n_fp / 300 == pytest.approx(0.3, abs=0.08)
    chair_u0 = np.array([d.xyxy_px[0] for ds in dets for d in ds
                         if d.class_name == "chair" and abs(d.xyxy_px[0] - 100) < 20])
    assert chair_u0.std() == pytest.approx(4.0, rel=0.2)
    for ds in dets:
        assert [d.score for d in ds] == sorted((d.score for d in ds), reverse=True)
        for d in ds:
            u0, v0, u1, v1 = d.xyxy_px
            assert 0 <= u0 < u1 <= 640 and 0 <= v0 < v1 <= 480
