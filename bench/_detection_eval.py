"""Scoring a detector against ground-truth boxes (``bench/detector.py``).

A frame's ground truth is ``(boxes (N, 4) xyxy px, class ids (N,), ignore (N,) bool)``: ignored
objects (too few visible pixels) are neither required nor counted as false positives when
detected. :func:`coco_ap50` is pycocotools' AP at IoU 0.5; the rest scores the detections at
one operating point (a score threshold) by greedy matching at IoU 0.5 per class, and says where
the errors are.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from typing import Any

import numpy as np

from semmap.tracking.matching import iou_matrix
from semmap.types import Detection

GroundTruth = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class FrameMatch:
    """One frame scored at the operating point: its detections at or above the score
    threshold (highest score first), their IoU with the ground truth (D, G), whether each
    ground-truth object was found, and each detection's outcome: ``tp``, ``ignored`` (it
    matches only ignored ground truth), or why it is a false positive: ``duplicate`` (its
    object was already found), ``wrong_class`` (another class's object), ``loose_box`` (its
    object at IoU 0.1-0.5) or ``background``."""

    dets: list[Detection]
    iou: np.ndarray
    found: np.ndarray
    outcomes: list[str]


def match(
    gts: list[GroundTruth], dets: list[list[Detection]],
    class_names: list[str], score_threshold: float, iou_threshold: float = 0.5,
) -> list[FrameMatch]:
    """Greedy per-class matching at ``score_threshold``, per frame: a detection finds the
    unfound object of its class it overlaps most at IoU >= ``iou_threshold``."""
    out = []
    for (g_boxes, g_cls, g_ignore), frame_dets in zip(gts, dets, strict=True):
        ds = sorted((d for d in frame_dets if d.score >= score_threshold), key=lambda d: -d.score)
        iou = iou_matrix(np.array([d.xyxy_px for d in ds], dtype=np.float64), g_boxes)
        found = np.zeros(len(g_boxes), dtype=bool)
        outcomes: list[str] = []
        for i, d in enumerate(ds):
            same = g_cls == class_names.index(d.class_name)
            hit = iou[i] >= iou_threshold
            cand = np.where(same & ~found & ~g_ignore & hit)[0]
            if len(cand):
                found[cand[np.argmax(iou[i, cand])]] = True
                outcomes.append("tp")
            elif np.any(same & g_ignore & hit):
                outcomes.append("ignored")
            elif np.any(same & hit):
                outcomes.append("duplicate")
            elif np.any(~same & ~g_ignore & hit):
                outcomes.append("wrong_class")
            elif np.any(same & ~g_ignore & (iou[i] >= 0.1)):
                outcomes.append("loose_box")
            else:
                outcomes.append("background")
        out.append(FrameMatch(ds, iou, found, outcomes))
    return out


def match_counts(
    gts: list[GroundTruth], matched: list[FrameMatch], class_names: list[str],
) -> dict[str, dict[str, int]]:
    """Per class TP/FP/FN; detections matching only ignored ground truth are neither."""
    out = {c: {"tp": 0, "fp": 0, "fn": 0} for c in class_names}
    for (_, g_cls, g_ignore), fm in zip(gts, matched, strict=True):
        for d, what in zip(fm.dets, fm.outcomes, strict=True):
            if what != "ignored":
                out[d.class_name]["tp" if what == "tp" else "fp"] += 1
        for k, name in enumerate(class_names):
            out[name]["fn"] += int(np.sum((g_cls == k) & ~g_ignore & ~fm.found))
    return out


def error_breakdown(
    gts: list[GroundTruth], matched: list[FrameMatch], class_names: list[str],
    width_px: int = 640, height_px: int = 480,
) -> dict[str, Any]:
    """Where the errors are at the operating point. Each missed object is counted once, as
    ``wrong_class`` (a detection of another class covers it at IoU >= 0.5), ``loose_box`` (one
    of its class at IoU 0.1-0.5) or ``missed``; and the recall of objects by kind: cut by the
    image border or whole, and by box area (COCO's small < 32^2, medium < 96^2 px, large).
    False positives by kind, and the wrong-class ones by ``true->detected`` class pair (the
    other class's object the detection covers best)."""
    miss = {"wrong_class": 0, "loose_box": 0, "missed": 0}
    groups: dict[str, list[int]] = {k: [0, 0] for k in
                                    ("border_cut", "whole", "small", "medium", "large")}
    fp: dict[str, int] = {"duplicate": 0, "wrong_class": 0, "loose_box": 0, "background": 0}
    confused: dict[str, int] = {}
    for (g_boxes, g_cls, g_ignore), fm in zip(gts, matched, strict=True):
        dc = np.array([class_names.index(d.class_name) for d in fm.dets], dtype=np.int64)
        for j in np.where(~g_ignore)[0]:
            u0, v0, u1, v1 = g_boxes[j]
            area = (u1 - u0) * (v1 - v0)
            cut = u0 <= 1 or v0 <= 1 or u1 >= width_px - 1 or v1 >= height_px - 1
            size = "small" if area < 32 ** 2 else "medium" if area < 96 ** 2 else "large"
            for g in ("border_cut" if cut else "whole", size):
                groups[g][0] += 1
                groups[g][1] += int(fm.found[j])
            if fm.found[j]:
                continue
            same, iou = dc == g_cls[j], fm.iou[:, j]
            if np.any(~same & (iou >= 0.5)):
                miss["wrong_class"] += 1
            elif np.any(same & (iou >= 0.1)):
                miss["loose_box"] += 1
            else:
                miss["missed"] += 1
        for i, what in enumerate(fm.outcomes):
            if what in fp:
                fp[what] += 1
            if what == "wrong_class":
                iou = np.where((g_cls == dc[i]) | g_ignore, -1.0, fm.iou[i])
                pair = f"{class_names[int(g_cls[int(np.argmax(iou))])]}->{class_names[dc[i]]}"
                confused[pair] = confused.get(pair, 0) + 1
    return {
        "false_negatives": miss,
        "false_positives": fp,
        "confused_true_to_detected": dict(sorted(confused.items(), key=lambda kv: -kv[1])),
        "recall_by_kind": {g: {"objects": n, "recall": round(k / n, 4) if n else None}
                           for g, (n, k) in groups.items()},
    }


def coco_ap50(
    gts: list[GroundTruth], dets: list[list[Detection]],
    class_names: list[str],
) -> tuple[float, dict[str, float], dict[str, float]]:
    """COCOeval AP at IoU 0.5: (mean over classes, per class, mean over classes by COCO's box
    area ranges small / medium / large). -1 for a class with no ground truth."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images, anns, results = [], [], []
    for img_id, ((g_boxes, g_cls, g_ignore), frame_dets) in enumerate(zip(gts, dets, strict=True), 1):
        images.append({"id": img_id, "width": 640, "height": 480})
        for (u0, v0, u1, v1), c, ign in zip(g_boxes.tolist(), g_cls.tolist(), g_ignore.tolist(), strict=True):
            anns.append({
                "id": len(anns) + 1, "image_id": img_id, "category_id": int(c) + 1,
                "bbox": [u0, v0, u1 - u0, v1 - v0], "area": (u1 - u0) * (v1 - v0), "iscrowd": int(ign),
            })
        for d in frame_dets:
            u0, v0, u1, v1 = d.xyxy_px
            results.append({"image_id": img_id, "category_id": class_names.index(d.class_name) + 1,
                            "bbox": [u0, v0, u1 - u0, v1 - v0], "score": d.score})
    coco = COCO()
    coco.dataset = {"images": images, "annotations": anns,
                    "categories": [{"id": i + 1, "name": n} for i, n in enumerate(class_names)]}
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
        dt = coco.loadRes(results) if results else COCO()
        ev = COCOeval(coco, dt, iouType="bbox")
        ev.evaluate()
        ev.accumulate()
    # precision: (IoU thresholds, recall points, classes, area ranges all/small/medium/large, max dets)
    def mean_ap(prec: np.ndarray) -> tuple[float, list[float]]:
        aps = [float(p[p > -1].mean()) if np.any(p > -1) else -1.0 for p in prec.T]
        valid = [v for v in aps if v >= 0]
        return (float(np.mean(valid)) if valid else -1.0), aps

    overall, aps = mean_ap(ev.eval["precision"][0, :, :, 0, -1])
    by_area = {name: round(mean_ap(ev.eval["precision"][0, :, :, a, -1])[0], 4)
               for a, name in ((1, "small"), (2, "medium"), (3, "large"))}
    return max(overall, 0.0), dict(zip(class_names, aps, strict=True)), by_area


#: Visible-fraction bins (occlusion and truncation together) the bench reports recall in.
VISIBILITY_BINS = ((0.0, 0.1), (0.1, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.0))


def by_visibility(
    gts: list[GroundTruth], visible_fraction: list[np.ndarray], matched: list[FrameMatch],
    dets: list[list[Detection]], class_names: list[str], min_fractions: tuple[float, ...] = (0.1, 0.25, 0.5),
) -> dict[str, Any]:
    """How the scores depend on how much of each object shows. ``visible_fraction`` holds,
    per frame, each ground-truth object's visible pixels over its unoccluded silhouette
    (``LabeledImage.visible_fraction``). Returns the objects (not already ignored) and
    their recall at the operating point per :data:`VISIBILITY_BINS` bin, and COCO AP@0.5
    (mean over classes) with the objects below each of ``min_fractions`` ignored as well:
    the figure a KITTI-style rule that does not ask for barely visible objects would give."""
    bins: dict[str, dict[str, Any]] = {}
    for lo, hi in VISIBILITY_BINS:
        n = k = 0
        for (_, _, g_ignore), vf, fm in zip(gts, visible_fraction, matched, strict=True):
            sel = ~g_ignore & (vf >= lo) & ((vf < hi) if hi < 1.0 else (vf <= hi))
            n += int(sel.sum())
            k += int(fm.found[sel].sum())
        bins[f"{lo:g}-{hi:g}"] = {"objects": n, "recall": round(k / n, 4) if n else None}
    map50 = {}
    for f in min_fractions:
        g2 = [(b, c, ign | (vf < f)) for (b, c, ign), vf in zip(gts, visible_fraction, strict=True)]
        map50[f"{f:g}"] = round(coco_ap50(g2, dets, class_names)[0], 4)
    return {"recall_by_visible_fraction": bins, "map50_ignoring_visible_below": map50}


def bootstrap_map50(
    gts: list[GroundTruth], dets: list[list[Detection]], class_names: list[str],
    frames_per_room: int, n_resamples: int = 200, seed: int = 0, level: float = 0.95,
) -> tuple[float, float]:
    """Percentile bootstrap interval of COCO mAP@0.5 over rooms: the frames of one room share
    its furniture, so they are resampled together (a per-frame bootstrap would count 15 views
    of the same table as 15 independent trials and give too narrow an interval). The frames
    are in room order, ``frames_per_room`` each. Returns (low, high) at ``level``: how far the
    headline figure could move on another draw of held-out rooms of the same kind."""
    if frames_per_room < 1 or len(gts) % frames_per_room:
        raise ValueError(f"{len(gts)} frames do not split into rooms of {frames_per_room} frames")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1) (got {level})")
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be at least 1 (got {n_resamples})")
    n_rooms = len(gts) // frames_per_room
    rng = np.random.default_rng(seed)
    maps = []
    for _ in range(n_resamples):
        rooms = rng.integers(0, n_rooms, n_rooms)
        idx = [r * frames_per_room + k for r in rooms.tolist() for k in range(frames_per_room)]
        maps.append(coco_ap50([gts[i] for i in idx], [dets[i] for i in idx], class_names)[0])
    tail = (1.0 - level) / 2.0 * 100.0
    lo, hi = np.percentile(maps, [tail, 100.0 - tail])
    return float(lo), float(hi)
