"""The hand labels of the real colour frames (tests/data/real_furniture_labels.json) and the
scoring that ``bench/detector.py --real`` does with them."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from bench._detection_eval import match  # noqa: E402
from bench._detector_real import (  # noqa: E402
    LABELS,
    LabelledFrame,
    detections_on_unnamed,
    ground_truth,
    to_eval_classes,
)
from semmap.types import Detection  # noqa: E402

DOC = json.loads(LABELS.read_text(encoding="utf-8"))
#: All three labelled sets are in the CI's ../shared/data; tests/data/real has the dining room.
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()
KNOWN = {"chair", "table", "sofa", "whiteboard"}
#: Where each set keeps its colour frames and how they are named.
COLOUR = {"diningroom": "*.png", "tum_fr1_desk": "*_color.png", "iclnuim_livingroom": "*_color.png"}


def test_the_labels_say_how_they_were_made_and_where_the_frames_come_from() -> None:
    assert "by hand" in DOC["method"] and "looked at" in DOC["method"]
    assert set(DOC["sets"]) == set(COLOUR)
    for s in DOC["sets"].values():
        assert s["origin"] and s["folder"].startswith("rgbd/")


def test_every_box_is_a_proper_box_of_a_known_kind_in_the_image() -> None:
    for name, s in DOC["sets"].items():
        for file_name, f in s["frames"].items():
            for o in f["objects"]:
                where = f"{name}/{file_name} {o}"
                assert o["class"] in KNOWN or o["class"].startswith("other:"), where
                u0, v0, u1, v1 = o["xyxy"]
                assert 0 <= u0 < u1 <= 640 and 0 <= v0 < v1 <= 480, where


@pytest.mark.skipif(not SHARED_DATA.is_dir(), reason=f"{SHARED_DATA} (the labelled sets) not found")
def test_every_real_colour_frame_is_labelled() -> None:
    for name, s in DOC["sets"].items():
        on_disk = sorted(p.name for p in (SHARED_DATA / s["folder"]).glob(COLOUR[name]))
        assert on_disk and sorted(s["frames"]) == on_disk, name


def test_tables_are_one_class_and_unmapped_classes_are_dropped() -> None:
    dets = [Detection((0, 0, 10, 10), 0.9, "desk"), Detection((0, 0, 10, 10), 0.8, "conference_table"),
            Detection((0, 0, 10, 10), 0.7, "whiteboard"), Detection((0, 0, 10, 10), 0.6, "chair")]
    out = to_eval_classes(dets, ["chair", "table", "sofa"])
    assert [d.class_name for d in out] == ["table", "table", "chair"]


def test_difficult_objects_are_ignored_and_other_kinds_left_out_of_the_ground_truth() -> None:
    frame = LabelledFrame("s", "f.png", Path("f.png"), [
        {"class": "chair", "xyxy": [0, 0, 10, 10]},
        {"class": "chair", "xyxy": [20, 0, 30, 10], "difficult": True},
        {"class": "other:cabinet", "xyxy": [40, 0, 90, 90]},
    ])
    boxes, cls, ignore = ground_truth(frame, ["chair", "table"])
    assert boxes.shape == (2, 4) and cls.tolist() == [0, 0] and ignore.tolist() == [False, True]


def test_a_detection_lying_on_a_cabinet_is_counted_against_it() -> None:
    frame = LabelledFrame("s", "f.png", Path("f.png"), [
        {"class": "other:cabinet", "xyxy": [100, 100, 200, 300]},
        {"class": "whiteboard", "xyxy": [300, 0, 400, 100]},
    ])
    dets = [Detection((110, 150, 190, 290), 0.5, "chair"),   # inside the cabinet
            Detection((0, 0, 50, 50), 0.5, "chair"),         # elsewhere
            Detection((290, 0, 390, 90), 0.5, "table")]     # on the whiteboard
    out = detections_on_unnamed([frame], [dets], ["chair", "table"], [["background"] * 3])
    assert out == {"cabinet": {"objects": 1, "detections": 1}, "whiteboard": {"objects": 1, "detections": 1}}
    # A model that names whiteboards is scored on them, not counted apart.
    out2 = detections_on_unnamed([frame], [dets], ["chair", "whiteboard"], [["background"] * 3])
    assert out2 == {"cabinet": {"objects": 1, "detections": 1}}


@pytest.mark.parametrize("model", ["builtin:coco"])
def test_the_coco_model_sees_no_furniture_on_the_ceiling_fan_or_the_cabinet(real_data: Path, model: str) -> None:
    """The phantoms that made the furniture model unusable on a real camera: the default real
    camera model, at its own operating point, puts nothing on them."""
    import cv2

    from companion.config import CompanionConfig
    from semmap.detection import detector_from_config
    from semmap.detection.onnx_detector import OnnxDetector

    ours = [c.name for c in CompanionConfig().classes]
    det = detector_from_config(CompanionConfig().detector.model_copy(
        update={"model_path": model, "providers": ["CPUExecutionProvider"]}), ours)
    assert isinstance(det, OnnxDetector)
    s = DOC["sets"]["diningroom"]
    for file_name in ("1.png", "2.png"):
        f = s["frames"][file_name]
        rgb = cv2.cvtColor(cv2.imread(str(real_data / s["folder"] / file_name)), cv2.COLOR_BGR2RGB)
        dets = det.detect(rgb)
        frame = LabelledFrame("diningroom", file_name, Path(file_name), f["objects"])
        classes = ["chair", "table", "sofa"]
        m = match([ground_truth(frame, classes)], [to_eval_classes(dets, classes)], classes, 0.0)[0]
        unnamed = detections_on_unnamed([frame], [m.dets], classes, [m.outcomes])
        for kind in ("ceiling_fan", "cabinet"):
            assert unnamed.get(kind, {"detections": 0})["detections"] == 0, (file_name, kind, dets)
