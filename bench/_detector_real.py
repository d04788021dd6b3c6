"""``bench/detector.py --real``: the shipped models on hand-labelled real colour frames.

The frames are every colour frame of the three real-image sets in ``../shared/data/rgbd``
(dining room, TUM fr1 desk, ICL-NUIM living room), labelled by hand in
``tests/data/real_furniture_labels.json`` (method and origin in the file). Each model
(``builtin:coco``, ``builtin:furniture``) runs through our runtime with one intra-op thread.

Scoring: our three table classes are one, ``table`` (COCO has one table class, and a box in an
image cannot tell a desk from a conference table; the object map does that from geometry). A
model is scored on the labelled classes it names: chair, table, sofa, and whiteboard for the
furniture model (COCO has no whiteboard). ``difficult`` objects are COCO's ``iscrowd``
(neither required nor false positives). Precision and recall at the operating point (the
config's ``detector.score_threshold``) by greedy matching at IoU 0.5, and COCOeval AP@0.5 per
class, as ``bench/_detection_eval.py`` does for the simulated rooms. Objects no class of ours
names (``other:*`` labels: cabinet, ceiling fan, ...) and whiteboards for a model without the
class are counted apart: the detections on each kind at the operating point (a detection is
on an object when at least half its box lies inside the object's box and it matches no
labelled object of its class).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench._detection_eval import GroundTruth, coco_ap50, match, match_counts
from companion.config import CompanionConfig
from semmap.detection import detector_from_config
from semmap.detection.builtin import builtin_defaults, effective_operating_point
from semmap.detection.onnx_detector import OnnxDetector
from semmap.types import Detection

REPO = Path(__file__).resolve().parents[1]
LABELS = REPO / "tests" / "data" / "real_furniture_labels.json"
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()
#: Our classes as the labels name them (the three table kinds are one ``table``).
EVAL_CLASS = {"chair": "chair", "sofa": "sofa", "desk": "table", "coffee_table": "table",
              "conference_table": "table", "whiteboard": "whiteboard"}
MODELS = {"coco": "builtin:coco", "furniture": "builtin:furniture"}
#: The labelled classes each model can name.
MODEL_CLASSES = {"coco": ["chair", "table", "sofa"], "furniture": ["chair", "table", "sofa", "whiteboard"]}


@dataclass(frozen=True)
class LabelledFrame:
    set_name: str
    file_name: str
    path: Path
    objects: list[dict[str, Any]]


def load_labels(labels_path: Path = LABELS, data_dir: Path = SHARED_DATA) -> list[LabelledFrame]:
    """Every labelled frame, its image path under ``data_dir``. Raises FileNotFoundError
    naming the folder when the real data is missing."""
    doc = json.loads(labels_path.read_text(encoding="utf-8"))
    out = []
    for set_name, s in doc["sets"].items():
        folder = data_dir / s["folder"]
        if not folder.is_dir():
            raise FileNotFoundError(f"real frames of {set_name} not found at {folder} (../shared/data)")
        for file_name, f in s["frames"].items():
            out.append(LabelledFrame(set_name, file_name, folder / file_name, list(f["objects"])))
    return out


def ground_truth(frame: LabelledFrame, classes: Sequence[str]) -> GroundTruth:
    """Boxes, class ids into ``classes`` and the ignore flags of the objects of those classes."""
    objs = [o for o in frame.objects if o["class"] in classes]
    boxes = np.array([o["xyxy"] for o in objs], dtype=np.float64).reshape(-1, 4)
    cls = np.array([list(classes).index(o["class"]) for o in objs], dtype=np.int64)
    ignore = np.array([bool(o.get("difficult", False)) for o in objs], dtype=bool)
    return boxes, cls, ignore


def to_eval_classes(dets: Sequence[Detection], classes: Sequence[str]) -> list[Detection]:
    """Detections in the labels' classes (tables merged); others dropped."""
    out = []
    for d in dets:
        c = EVAL_CLASS.get(d.class_name)
        if c in classes:
            out.append(Detection(d.xyxy_px, d.score, c))
    return out


def _inside_frac(det_xyxy: Sequence[float], box: Sequence[float]) -> float:
    u0, v0 = max(det_xyxy[0], box[0]), max(det_xyxy[1], box[1])
    u1, v1 = min(det_xyxy[2], box[2]), min(det_xyxy[3], box[3])
    inter = max(0.0, u1 - u0) * max(0.0, v1 - v0)
    area = max(1e-9, (det_xyxy[2] - det_xyxy[0]) * (det_xyxy[3] - det_xyxy[1]))
    return inter / area


def detections_on_unnamed(
    frames: Sequence[LabelledFrame], dets: Sequence[Sequence[Detection]], classes: Sequence[str],
    outcomes: Sequence[Sequence[str]],
) -> dict[str, dict[str, int]]:
    """Per kind of object the model's classes do not name: how many there are, and how many
    detections (not true positives) lie at least half on one."""
    out: dict[str, dict[str, int]] = {}
    for frame, frame_dets, frame_outcomes in zip(frames, dets, outcomes, strict=True):
        unnamed = [o for o in frame.objects if o["class"].startswith("other:")
                   or (o["class"] == "whiteboard" and "whiteboard" not in classes)]
        for o in unnamed:
            kind = o["class"].removeprefix("other:")
            row = out.setdefault(kind, {"objects": 0, "detections": 0})
            row["objects"] += 1
            row["detections"] += sum(
                1 for d, what in zip(frame_dets, frame_outcomes, strict=True)
                if what != "tp" and _inside_frac(d.xyxy_px, o["xyxy"]) >= 0.5)
    return dict(sorted(out.items()))


def run_real(score_threshold: float | None, repeats: int, data_dir: Path = SHARED_DATA) -> dict[str, Any]:
    """Score both shipped models on the labelled real frames; returns the JSON figures and
    prints the table."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    cfg = CompanionConfig()
    our_classes = [c.name for c in cfg.classes]
    frames = load_labels(data_dir=data_dir)
    images = [cv2.cvtColor(cv2.imread(str(f.path)), cv2.COLOR_BGR2RGB) for f in frames]
    n_obj = {c: sum(1 for f in frames for o in f.objects if o["class"] == c and not o.get("difficult"))
             for c in ("chair", "table", "sofa", "whiteboard")}
    print(f"real frames: {len(frames)} ({', '.join(sorted({f.set_name for f in frames}))}); labelled objects "
          f"(not difficult): " + ", ".join(f"{k} {v}" for k, v in n_obj.items()))
    print(f"operating point: each model's own (its detector.score_threshold default), or "
          f"--score-threshold; ONNX Runtime CPU, 1 intra-op thread, load average {os.getloadavg()[0]:.1f}")
    result: dict[str, Any] = {"frames": len(frames), "models": {}}
    for key, model_path in MODELS.items():
        dcfg = cfg.detector.model_copy(update={
            "kind": "onnx", "model_path": model_path, "providers": ["CPUExecutionProvider"],
            "intra_op_threads": 1, "score_threshold": 0.001,
            "class_score_thresholds": {c: 0.001 for c in our_classes}})
        det = detector_from_config(dcfg, our_classes)
        assert isinstance(det, OnnxDetector)
        classes = MODEL_CLASSES[key]
        score, per_class_th, _ = effective_operating_point(
            score_threshold, {}, None, builtin_defaults(det.model_path), our_classes)
        if score_threshold is not None:
            per_class_th = {}
        raw, ms = [], []
        for img in images:
            for r in range(repeats):
                t0 = time.perf_counter()
                d = det.detect(img)
                ms.append((time.perf_counter() - t0) * 1e3)
                if r == 0:
                    raw.append(d)
        dets = [to_eval_classes(d, classes) for d in raw]
        gts = [ground_truth(f, classes) for f in frames]
        _, ap50, _ = coco_ap50(gts, dets, classes)
        # The operating point per our class, then matching of what passes it.
        at_op = [to_eval_classes([d for d in frame_raw if d.score >= per_class_th.get(d.class_name, score)],
                                 classes) for frame_raw in raw]
        matched = match(gts, at_op, classes, 0.0)
        counts = match_counts(gts, matched, classes)
        tp = sum(c["tp"] for c in counts.values())
        fp = sum(c["fp"] for c in counts.values())
        fn = sum(c["fn"] for c in counts.values())
        per_class = {c: {"instances": int(sum(np.sum((g[1] == i) & ~g[2]) for g in gts)),
                         "precision": round(counts[c]["tp"] / max(1, counts[c]["tp"] + counts[c]["fp"]), 4),
                         "recall": round(counts[c]["tp"] / max(1, counts[c]["tp"] + counts[c]["fn"]), 4),
                         "false_positives": counts[c]["fp"]}
                     for i, c in enumerate(classes)}
        unnamed = detections_on_unnamed(frames, [m.dets for m in matched], classes,
                                        [m.outcomes for m in matched])
        tables_found = sum(int(np.sum(m.found & (g[1] == classes.index("table")) & ~g[2]))
                           for m, g in zip(matched, gts, strict=True))
        dining = [(m.found[j], f) for f, m, g in zip(frames, matched, gts, strict=True)
                  for j, o in enumerate(o for o in f.objects if o["class"] in classes)
                  if o["class"] == "table" and str(o.get("note", "")).startswith("dining table")]
        by_set: dict[str, dict[str, int]] = {}
        for f, m in zip(frames, matched, strict=True):
            row = by_set.setdefault(f.set_name, {"tp": 0, "fp": 0})
            row["tp"] += m.outcomes.count("tp")
            row["fp"] += sum(1 for o in m.outcomes if o not in ("tp", "ignored"))
        result["models"][key] = {
            "model": det.model_path.name,
            "operating_point": {"score_threshold": score, "class_score_thresholds": per_class_th},
            "classes": classes,
            "precision": round(tp / max(1, tp + fp), 4),
            "recall": round(tp / max(1, tp + fn), 4),
            "ap50": {c: round(ap50[c], 4) for c in classes},
            "per_class": per_class,
            "tables_found": tables_found,
            "dining_tables": {"instances": len(dining), "found": int(sum(bool(k) for k, _ in dining))},
            "detections_on_unnamed": unnamed,
            "by_set": by_set,
            "latency_ms_p50": round(float(np.percentile(ms, 50)), 2),
            "latency_ms_p95": round(float(np.percentile(ms, 95)), 2),
        }
        r = result["models"][key]
        print()
        print(f"{key}: {det.model_path.name}, input {det.input_hw_px[1]}x{det.input_hw_px[0]}, "
              f"{det.head} head; classes scored: {', '.join(classes)}; operating point score >= {score}"
              + "".join(f", {k} >= {v}" for k, v in per_class_th.items()))
        print(f"  all     P {r['precision']:.3f}  R {r['recall']:.3f}   latency p50 {r['latency_ms_p50']:.1f} ms, "
              f"p95 {r['latency_ms_p95']:.1f} ms ({len(ms)} runs)")
        for c in classes:
            pc = per_class[c]
            print(f"  {c:<10} {pc['instances']:>3} objects  P {pc['precision']:.3f}  R {pc['recall']:.3f}  "
                  f"AP@0.5 {r['ap50'][c]:.3f}  false positives {pc['false_positives']}")
        print(f"  tables found {tables_found} of {n_obj['table']} (dining table {r['dining_tables']['found']} of "
              f"{r['dining_tables']['instances']}); by set (TP/FP): " + ", ".join(
            f"{k} {v['tp']}/{v['fp']}" for k, v in by_set.items()))
        print("  detections on objects it cannot name (detections/objects): " + ", ".join(
            f"{k} {v['detections']}/{v['objects']}" for k, v in unnamed.items()))
    return result
