"""Accuracy and speed of the shipped furniture detector on held-out simulated rooms.

Run ``python bench/detector.py`` (20 held-out rooms x 15 images, the held-out split of
``semmap/models/MODEL_CARD.md``) or ``--quick`` (4 rooms x 6 images). The model is the one the
config's ``builtin:furniture`` names, run through our own runtime
(:class:`semmap.detection.onnx_detector.OnnxDetector`: letterbox, ONNX Runtime with one
intra-op thread, decode, class-aware NMS), on frames rendered on the fly from room seeds that
training never saw (:func:`companion.sim.dataset.room_seeds` ``"heldout"``).

Evaluation: pycocotools' COCOeval on boxes in original-image pixels. Ground truth is the tight
box of each object's visible pixels; objects with fewer than ``--min-visible-px`` (120) visible
pixels are marked ``iscrowd`` (ignored: neither required nor counted as false positives when
detected), the same rule the training labels use. AP@0.5 per class is COCO's 101-point
interpolated AP at IoU 0.5 (detections kept down to score 0.001, COCO's protocol); mAP@0.5 is
its mean over classes. Precision and recall are at the runtime's operating point
(``detector.score_threshold``, 0.25 by default), greedy matching at IoU 0.5 per class.
Inference time is the whole :meth:`OnnxDetector.detect` per 640x480 frame.

The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.config import CompanionConfig  # noqa: E402
from companion.sim.dataset import DatasetSpec, generate, room_seeds  # noqa: E402
from semmap.detection import BUILTIN_MODELS_DIR, detector_from_config  # noqa: E402
from semmap.detection.onnx_detector import OnnxDetector  # noqa: E402
from semmap.types import Detection  # noqa: E402


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) IoU of xyxy boxes (N, 4) and (M, 4)."""
    tl = np.maximum(a[:, None, :2], b[None, :, :2])
    br = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(br - tl, 0.0, None), axis=2)
    area_a = np.prod(a[:, 2:] - a[:, :2], axis=1)
    area_b = np.prod(b[:, 2:] - b[:, :2], axis=1)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def _match_counts(
    gts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], dets: list[list[Detection]],
    class_names: list[str], score_threshold: float, iou_threshold: float = 0.5,
) -> dict[str, dict[str, int]]:
    """Per class TP/FP/FN at ``score_threshold``; detections matching only ignored ground
    truth are neither TP nor FP."""
    out = {c: {"tp": 0, "fp": 0, "fn": 0} for c in class_names}
    for (g_boxes, g_cls, g_ignore), frame_dets in zip(gts, dets, strict=True):
        for k, name in enumerate(class_names):
            gsel = g_cls == k
            gb, gi = g_boxes[gsel], g_ignore[gsel]
            ds = sorted((d for d in frame_dets if d.class_name == name and d.score >= score_threshold),
                        key=lambda d: -d.score)
            db = np.array([d.xyxy_px for d in ds], dtype=np.float64).reshape(-1, 4)
            taken = np.zeros(len(gb), dtype=bool)
            iou = _iou(db, gb) if len(db) and len(gb) else np.zeros((len(db), len(gb)))
            for i in range(len(db)):
                cand = np.where(~taken & ~gi & (iou[i] >= iou_threshold))[0]
                if len(cand):
                    taken[cand[np.argmax(iou[i, cand])]] = True
                    out[name]["tp"] += 1
                elif not np.any(gi & (iou[i] >= iou_threshold)):
                    out[name]["fp"] += 1
            out[name]["fn"] += int(np.sum(~taken & ~gi))
    return out


def _coco_ap50(
    gts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], dets: list[list[Detection]],
    class_names: list[str],
) -> tuple[float, dict[str, float]]:
    """COCOeval AP at IoU 0.5: (mean over classes, per class). -1 for a class with no ground truth."""
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
    prec = ev.eval["precision"][0, :, :, 0, -1]  # (recall points, classes) at IoU 0.5, all areas, 100 dets
    per_class = {}
    for k, name in enumerate(class_names):
        p = prec[:, k]
        per_class[name] = float(p[p > -1].mean()) if np.any(p > -1) else -1.0
    valid = [v for v in per_class.values() if v >= 0]
    return (float(np.mean(valid)) if valid else 0.0), per_class


def _n_parameters(path: Path) -> int:
    import onnx

    model = onnx.load(str(path))
    return int(sum(int(np.prod(t.dims)) for t in model.graph.initializer))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 rooms x 6 images")
    ap.add_argument("--rooms", type=int, default=None)
    ap.add_argument("--images-per-room", type=int, default=None)
    ap.add_argument("--seed", type=int, default=1, help="held-out appearance/pose seed (model card: 1)")
    ap.add_argument("--min-visible-px", type=int, default=120)
    ap.add_argument("--model", default="builtin:furniture", help="ONNX path or builtin:NAME")
    args = ap.parse_args()
    n_rooms = args.rooms or (4 if args.quick else 20)
    per_room = args.images_per_room or (6 if args.quick else 15)

    cfg = CompanionConfig()
    class_names = [c.name for c in cfg.classes]
    dcfg = cfg.detector.model_copy(update={
        "kind": "onnx", "model_path": args.model, "providers": ["CPUExecutionProvider"],
        "intra_op_threads": 1, "score_threshold": 0.001, "class_score_thresholds": {},
    })
    detector = detector_from_config(dcfg, class_names)
    assert isinstance(detector, OnnxDetector)
    operating_threshold = cfg.detector.score_threshold

    spec = DatasetSpec(split="heldout", n_rooms=n_rooms, images_per_room=per_room, seed=args.seed,
                       class_names=tuple(class_names), intrinsics=cfg.camera.intrinsics(),
                       min_visible_px=1)
    gts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    dets: list[list[Detection]] = []
    infer_s: list[float] = []
    t_render = 0.0
    t0 = time.perf_counter()
    for item in generate(spec):
        t_render += time.perf_counter() - t0
        ignore = item.visible_px < args.min_visible_px
        gts.append((item.boxes_xyxy_px, item.class_ids, ignore))
        t1 = time.perf_counter()
        dets.append(detector.detect(item.rgb))
        infer_s.append(time.perf_counter() - t1)
        t0 = time.perf_counter()

    map50, ap50 = _coco_ap50(gts, dets, class_names)
    counts = _match_counts(gts, dets, class_names, operating_threshold)
    ms = np.asarray(infer_s) * 1e3
    n_params = _n_parameters(detector.model_path)
    n_img = len(gts)

    rows: dict[str, dict[str, Any]] = {}
    tp_all = fp_all = fn_all = 0
    for name in class_names:
        c = counts[name]
        tp_all, fp_all, fn_all = tp_all + c["tp"], fp_all + c["fp"], fn_all + c["fn"]
        n_inst = int(sum(np.sum((g[1] == class_names.index(name)) & ~g[2]) for g in gts))
        rows[name] = {
            "instances": n_inst,
            "precision": round(c["tp"] / max(1, c["tp"] + c["fp"]), 4),
            "recall": round(c["tp"] / max(1, c["tp"] + c["fn"]), 4),
            "ap50": round(ap50[name], 4),
        }
    overall = {
        "images": n_img,
        "instances": int(sum(r["instances"] for r in rows.values())),
        "precision": round(tp_all / max(1, tp_all + fp_all), 4),
        "recall": round(tp_all / max(1, tp_all + fn_all), 4),
        "map50": round(map50, 4),
    }

    print(f"model {detector.model_path.name} ({detector.model_path.stat().st_size / 1e6:.2f} MB, "
          f"{n_params / 1e6:.2f} M parameters, input {detector.input_hw_px[1]}x{detector.input_hw_px[0]}, "
          f"{detector.head} head)")
    print(f"held-out rooms: seeds {room_seeds('heldout', n_rooms)[0]}..{room_seeds('heldout', n_rooms)[-1]}, "
          f"{n_img} frames 640x480; P/R at score >= {operating_threshold}; "
          f"objects < {args.min_visible_px} visible px ignored")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}; ONNX Runtime CPU, 1 intra-op thread")
    print()
    print(f"{'class':<18}{'instances':>10}{'precision':>11}{'recall':>9}{'mAP@0.5':>10}")
    print(f"{'all':<18}{overall['instances']:>10}{overall['precision']:>11.3f}{overall['recall']:>9.3f}"
          f"{overall['map50']:>10.3f}")
    for name, r in rows.items():
        c = counts[name]
        ap_txt = f"{r['ap50']:>10.3f}" if r["ap50"] >= 0 else f"{'n/a':>10}"
        p_txt = f"{r['precision']:>11.3f}" if c["tp"] + c["fp"] else f"{'n/a':>11}"  # no detections
        r_txt = f"{r['recall']:>9.3f}" if r["instances"] else f"{'n/a':>9}"
        print(f"{name:<18}{r['instances']:>10}{p_txt}{r_txt}{ap_txt}")
    print()
    print(f"parameters: {n_params:,}   inference per frame (letterbox + ONNX Runtime + decode + NMS): "
          f"p50 {np.percentile(ms, 50):.1f} ms, p95 {np.percentile(ms, 95):.1f} ms, mean {ms.mean():.1f} ms"
          f"   (rendering took {t_render:.0f} s)")
    result = {
        "model": detector.model_path.name,
        "model_bytes": detector.model_path.stat().st_size,
        "parameters": n_params,
        "input_px": detector.input_hw_px[1],
        "heldout_rooms": n_rooms,
        "overall": overall,
        "per_class": rows,
        "inference": {
            "p50_ms": round(float(np.percentile(ms, 50)), 2),
            "p95_ms": round(float(np.percentile(ms, 95)), 2),
            "mean_ms": round(float(ms.mean()), 2),
            "intra_op_threads": 1,
        },
        "load_average_1min": round(os.getloadavg()[0], 2),
        "models_dir": str(BUILTIN_MODELS_DIR),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
