"""The detector benchmark's scoring (bench/_detection_eval.py): what counts as found, what kind
of error each miss and false positive is, and the COCO AP it reports."""

from __future__ import annotations

import numpy as np
import pytest

from bench._detection_eval import (
    bootstrap_map50,
    by_visibility,
    coco_ap50,
    error_breakdown,
    match,
    match_counts,
)
from semmap.types import Detection

CLASSES = ["chair", "coffee_table", "desk"]


def _gt(boxes: list[tuple[float, float, float, float]], classes: list[int],
        ignore: list[bool] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.asarray(boxes, dtype=np.float64).reshape(-1, 4), np.asarray(classes, dtype=np.int64),
            np.asarray(ignore or [False] * len(classes), dtype=bool))


def _det(box: tuple[float, float, float, float], name: str, score: float = 0.9) -> Detection:
    return Detection(xyxy_px=box, score=score, class_name=name)


def test_each_detection_and_each_miss_gets_its_kind() -> None:
    gts = [_gt([(100, 100, 200, 200),    # chair, found (and found again: a duplicate)
                (300, 100, 400, 200),    # desk, detected as a coffee table
                (100, 300, 200, 400),    # chair, only a loose box on it
                (400, 300, 500, 400),    # coffee table, nothing near it
                (10, 10, 20, 20)],       # chair too small to be required
               [0, 2, 0, 1, 0], [False, False, False, False, True])]
    dets = [[
        _det((100, 100, 200, 200), "chair", 0.95),
        _det((102, 100, 200, 202), "chair", 0.90),
        _det((300, 100, 400, 200), "coffee_table", 0.8),
        _det((100, 300, 150, 330), "chair", 0.7),       # IoU 0.15 with its chair
        _det((10, 10, 20, 20), "chair", 0.6),           # on the ignored chair
        _det((550, 10, 600, 60), "desk", 0.5),          # nothing there
        _det((400, 300, 500, 400), "coffee_table", 0.1),  # below the operating point
    ]]
    matched = match(gts, dets, CLASSES, score_threshold=0.25)
    assert matched[0].found.tolist() == [True, False, False, False, False]
    assert matched[0].outcomes == [
        "tp", "duplicate", "wrong_class", "loose_box", "ignored", "background"]
    counts = match_counts(gts, matched, CLASSES)
    assert counts["chair"] == {"tp": 1, "fp": 2, "fn": 1}
    assert counts["coffee_table"] == {"tp": 0, "fp": 1, "fn": 1}
    assert counts["desk"] == {"tp": 0, "fp": 1, "fn": 1}
    errors = error_breakdown(gts, matched, CLASSES)
    assert errors["false_negatives"] == {"wrong_class": 1, "loose_box": 1, "missed": 1}
    assert errors["false_positives"] == {"duplicate": 1, "wrong_class": 1, "loose_box": 1, "background": 1}
    assert errors["confused_true_to_detected"] == {"desk->coffee_table": 1}
    by_kind = errors["recall_by_kind"]
    assert by_kind["whole"] == {"objects": 4, "recall": 0.25}
    assert by_kind["border_cut"] == {"objects": 0, "recall": None}
    assert by_kind["large"] == {"objects": 4, "recall": 0.25}


def test_objects_cut_by_the_border_and_small_ones_are_told_apart() -> None:
    gts = [_gt([(0, 50, 100, 150), (600, 400, 640, 480), (300, 200, 320, 220)], [0, 1, 2])]
    dets = [[_det((0, 50, 100, 150), "chair")]]
    matched = match(gts, dets, CLASSES, score_threshold=0.25)
    by_kind = error_breakdown(gts, matched, CLASSES)["recall_by_kind"]
    assert by_kind["border_cut"] == {"objects": 2, "recall": 0.5}
    assert by_kind["whole"] == {"objects": 1, "recall": 0.0}
    assert by_kind["small"] == {"objects": 1, "recall": 0.0}      # 20 x 20 px
    assert by_kind["medium"] == {"objects": 1, "recall": 0.0}     # 40 x 80 px
    assert by_kind["large"] == {"objects": 1, "recall": 1.0}


def test_coco_ap_is_one_for_perfect_detections_and_drops_with_a_confident_false_positive() -> None:
    pytest.importorskip("pycocotools")
    gts = [_gt([(100, 100, 200, 200), (300, 100, 400, 200)], [0, 2]),
           _gt([(100, 100, 300, 300)], [0])]
    perfect = [[_det((100, 100, 200, 200), "chair"), _det((300, 100, 400, 200), "desk")],
               [_det((100, 100, 300, 300), "chair")]]
    mean, per_class, by_area = coco_ap50(gts, perfect, CLASSES)
    assert mean == pytest.approx(1.0)
    assert per_class == {"chair": pytest.approx(1.0), "coffee_table": -1.0, "desk": pytest.approx(1.0)}
    assert by_area["large"] == pytest.approx(1.0) and by_area["small"] == -1.0
    # A chair detected, more confidently than both real chairs, where there is none: at the
    # first recall point the chair's precision is 1/2, so its AP falls below 1.
    worse = [perfect[0] + [_det((500, 300, 600, 400), "chair", 0.99)], perfect[1]]
    mean_worse, per_class_worse, _ = coco_ap50(gts, worse, CLASSES)
    assert per_class_worse["chair"] < 0.9 and per_class_worse["desk"] == pytest.approx(1.0)
    assert mean_worse < mean


def test_barely_visible_objects_are_scored_apart() -> None:
    """Recall per visible-fraction bin, and the AP once objects below a fraction are ignored:
    a missed sliver costs AP with every object counted, nothing once slivers are ignored."""
    gts = [_gt([(100, 100, 200, 200), (300, 100, 400, 200), (10, 10, 20, 20)], [0, 2, 0], [False, False, True])]
    vf = [np.array([0.9, 0.05, 0.5])]  # chair well in view, desk a sliver, an ignored speck
    dets = [[_det((100, 100, 200, 200), "chair", 0.9)]]
    matched = match(gts, dets, CLASSES, 0.25)
    out = by_visibility(gts, vf, matched, dets, CLASSES, min_fractions=(0.1,))
    bins = out["recall_by_visible_fraction"]
    assert bins["0.75-1"] == {"objects": 1, "recall": 1.0}
    assert bins["0-0.1"] == {"objects": 1, "recall": 0.0}
    assert bins["0.25-0.5"] == {"objects": 0, "recall": None}  # the ignored speck is not counted
    assert coco_ap50(gts, dets, CLASSES)[0] == pytest.approx(0.5)  # chair 1, desk 0
    assert out["map50_ignoring_visible_below"]["0.1"] == pytest.approx(1.0)  # desk has no required object left


def test_the_room_bootstrap_interval_brackets_the_figure_and_spans_what_rooms_disagree_on() -> None:
    pytest.importorskip("pycocotools")
    # Four rooms of two frames, one chair per frame. Two rooms detect it perfectly; in the other
    # two a confident phantom chair precedes the real one in every frame.
    gts, dets = [], []
    for room in range(4):
        for _ in range(2):
            gts.append(_gt([(100, 100, 200, 200)], [0]))
            good = [_det((100, 100, 200, 200), "chair", 0.5)]
            dets.append(good if room < 2 else good + [_det((400, 300, 500, 400), "chair", 0.9)])
    point = coco_ap50(gts, dets, CLASSES)[0]
    low, high = bootstrap_map50(gts, dets, CLASSES, frames_per_room=2, n_resamples=300)
    assert low < point < high
    assert high == pytest.approx(1.0)  # a draw of only the good rooms
    assert low < 0.6                   # a draw of mostly phantom rooms
    # Rooms that all score the same leave nothing to resample: the interval is the figure.
    perfect = [[_det((100, 100, 200, 200), "chair")] for _ in gts]
    assert bootstrap_map50(gts, perfect, CLASSES, frames_per_room=2, n_resamples=20) == (
        pytest.approx(1.0), pytest.approx(1.0))
    with pytest.raises(ValueError, match="rooms of 3 frames"):
        bootstrap_map50(gts, dets, CLASSES, frames_per_room=3)
    with pytest.raises(ValueError, match="n_resamples"):
        bootstrap_map50(gts, dets, CLASSES, frames_per_room=2, n_resamples=0)
