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
(``detector.score_threshold``, 0.25 for this model), greedy matching at IoU 0.5 per class
(``bench/_detection_eval.py``), with where the errors are: missed objects and false positives by
kind, class confusions, recall of border-cut vs whole objects and by COCO box-area range, and
mAP@0.5 by area range; a 95 % percentile-bootstrap interval of mAP@0.5 over rooms (a room's
frames resampled together: how far the figure would move on another draw of 20 rooms); and by
visibility: recall per visible-fraction bin (visible pixels over the unoccluded silhouette on
an image plane three times the size, so occlusion and truncation together) and, beside the
headline, mAP@0.5 with objects under 10, 25 or 50 % visible also ignored (a KITTI-style rule;
the headline asks for every object of 120 visible px or more). ``--rooms 100`` measures the
same model more tightly (about +-0.015 against +-0.025 for the default 20 rooms).
Inference time is the whole :meth:`OnnxDetector.detect` per 640x480 frame.

``--split val`` scores the validation rooms instead (room seeds 800000.., the split that picks
a training run's exported epoch): use it to choose between candidate models, so the held-out
figure stays a test figure and is not also the thing that chose the model.

``--split train --room-start N --seed 0`` scores rooms a model trained on (room seeds 100000+N..,
the same rooms ``companion dataset --split train --room-start N --seed 0`` rendered, seen from
the held-out protocol's poses): how well the model fits its own training rooms. Next to the
validation figure it tells an under-fitting model (both low: more rooms of the same kind will
not help) from an over-fitting one (training rooms much higher: more varied rooms will). Only
rooms rendered without ``--class-weights`` come out the same (the weights change the furniture).

``--real`` scores both shipped models (``builtin:coco``, ``builtin:furniture``) on the
hand-labelled real colour frames of ``../shared/data/rgbd`` instead (``bench/_detector_real.py``
says how): precision and recall at the operating point, AP@0.5 per class, detections on
objects no class of ours names, and the inference time with one thread.

``--world`` picks the rooms' layout: ``realistic`` (the default: chairs under tables, clutter on
desks) also scores the same room seeds laid out ``scattered``, so the drop is the layout's alone
(``--no-scattered`` skips that).

The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._detection_eval import (  # noqa: E402
    GroundTruth,
    bootstrap_map50,
    by_visibility,
    coco_ap50,
    error_breakdown,
    match,
    match_counts,
)
from companion.config import CompanionConfig  # noqa: E402
from companion.sim.dataset import DatasetSpec, generate, room_seeds  # noqa: E402
from companion.sim.world import LAYOUTS  # noqa: E402
from semmap.detection import BUILTIN_MODELS_DIR, detector_from_config  # noqa: E402
from semmap.detection.builtin import DEFAULT_SCORE_THRESHOLD  # noqa: E402
from semmap.detection.onnx_detector import OnnxDetector  # noqa: E402
from semmap.types import Detection  # noqa: E402


def _n_parameters(path: Path) -> int:
    import onnx

    model = onnx.load(str(path))
    return int(sum(int(np.prod(t.dims)) for t in model.graph.initializer))


def _run(spec: DatasetSpec, detector: OnnxDetector, args: argparse.Namespace) -> tuple[
        list[GroundTruth], list[list[Detection]], list[np.ndarray], list[float], float]:
    """Render the split's images and detect on each: ground truth, detections, visible
    fractions (empty without ``spec.measure_visibility``), inference and rendering times (s)."""
    gts: list[GroundTruth] = []
    visible_fraction: list[np.ndarray] = []
    dets: list[list[Detection]] = []
    infer_s: list[float] = []
    t_render = 0.0
    t0 = time.perf_counter()
    for item in generate(spec, room_start=args.room_start):
        t_render += time.perf_counter() - t0
        ignore = item.visible_px < args.min_visible_px
        gts.append((item.boxes_xyxy_px, item.class_ids, ignore))
        if item.visible_fraction is not None:
            visible_fraction.append(item.visible_fraction)
        t1 = time.perf_counter()
        dets.append(detector.detect(item.rgb))
        infer_s.append(time.perf_counter() - t1)
        t0 = time.perf_counter()
    return gts, dets, visible_fraction, infer_s, t_render


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 rooms x 6 images")
    ap.add_argument("--rooms", type=int, default=None)
    ap.add_argument("--images-per-room", type=int, default=None)
    ap.add_argument("--seed", type=int, default=1, help="held-out appearance/pose seed (model card: 1)")
    ap.add_argument("--min-visible-px", type=int, default=120)
    ap.add_argument("--model", default="builtin:furniture", help="ONNX path or builtin:NAME")
    ap.add_argument("--resamples", type=int, default=200, help="room bootstrap resamples for the mAP interval")
    ap.add_argument("--split", default="heldout", choices=("heldout", "val", "train"),
                    help="rooms to score: held-out (the headline), val (for choosing a model) or "
                         "train (how well a model fits rooms it trained on)")
    ap.add_argument("--world", choices=LAYOUTS, default="realistic", help="room layout of the scored rooms")
    ap.add_argument("--no-scattered", action="store_true",
                    help="with --world realistic: skip scoring the same rooms scattered")
    ap.add_argument("--room-start", type=int, default=0,
                    help="first room within the split (as for `companion dataset --room-start`)")
    ap.add_argument("--real", action="store_true",
                    help="score builtin:coco and builtin:furniture on the hand-labelled real frames")
    ap.add_argument("--score-threshold", type=float, default=None,
                    help="--real: the operating point (default: the config's detector.score_threshold)")
    ap.add_argument("--data", default=None, help="--real: the real data folder (default ../shared/data)")
    args = ap.parse_args()
    if args.real:
        from bench._detector_real import SHARED_DATA, run_real

        data = Path(args.data) if args.data else SHARED_DATA
        print(json.dumps(run_real(args.score_threshold, repeats=1 if args.quick else 3, data_dir=data)))
        return
    if args.resamples < 1:  # checked before minutes of rendering, not after
        ap.error(f"--resamples must be at least 1 (got {args.resamples})")
    if args.room_start < 0:
        ap.error(f"--room-start must be >= 0 (got {args.room_start})")
    n_rooms = args.rooms or (4 if args.quick else 20)
    per_room = args.images_per_room or (6 if args.quick else 15)

    cfg = CompanionConfig()
    class_names = [c.name for c in cfg.classes]
    dcfg = cfg.detector.model_copy(update={
        "kind": "onnx", "model_path": args.model, "providers": ["CPUExecutionProvider"],
        "intra_op_threads": 1, "score_threshold": 0.001,
        "class_score_thresholds": {c: 0.001 for c in class_names},
    })
    detector = detector_from_config(dcfg, class_names)
    assert isinstance(detector, OnnxDetector)
    operating_threshold = (DEFAULT_SCORE_THRESHOLD if cfg.detector.score_threshold is None
                           else cfg.detector.score_threshold)

    spec = DatasetSpec(split=args.split, n_rooms=n_rooms, images_per_room=per_room, seed=args.seed,
                       class_names=tuple(class_names), intrinsics=cfg.camera.intrinsics(),
                       min_visible_px=1, measure_visibility=True, layout=args.world)
    gts, dets, visible_fraction, infer_s, t_render = _run(spec, detector, args)
    scattered: dict[str, Any] | None = None
    if args.world == "realistic" and not args.no_scattered:
        # The same held-out seeds laid out scattered: the drop is the layout's alone.
        s_gts, s_dets, _, _, _ = _run(replace(spec, layout="scattered", measure_visibility=False), detector, args)
        s_map50, _, _ = coco_ap50(s_gts, s_dets, class_names)
        s_lo, s_hi = bootstrap_map50(s_gts, s_dets, class_names, per_room, n_resamples=args.resamples)
        scattered = {"map50": round(s_map50, 4), "map50_interval95_rooms": {"low": round(s_lo, 4), "high": round(s_hi, 4)}}

    map50, ap50, map50_by_area = coco_ap50(gts, dets, class_names)
    matched = match(gts, dets, class_names, operating_threshold)
    counts = match_counts(gts, matched, class_names)
    errors = error_breakdown(gts, matched, class_names)
    visibility = by_visibility(gts, visible_fraction, matched, dets, class_names)
    map50_lo, map50_hi = bootstrap_map50(gts, dets, class_names, per_room, n_resamples=args.resamples)
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
    seeds = room_seeds(args.split, n_rooms, start=args.room_start)
    split_text = {"heldout": "held-out", "val": "validation", "train": "training"}[args.split]
    print(f"{split_text} rooms: seeds {seeds[0]}..{seeds[-1]} (appearance seed {args.seed}), "
          f"{n_img} frames 640x480; P/R at score >= {operating_threshold}; "
          f"objects < {args.min_visible_px} visible px ignored")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}; ONNX Runtime CPU, 1 intra-op thread")
    print()
    print(f"{'class':<18}{'instances':>10}{'precision':>11}{'recall':>9}{'mAP@0.5':>10}")
    print(f"{'all':<18}{overall['instances']:>10}{overall['precision']:>11.3f}{overall['recall']:>9.3f}"
          f"{overall['map50']:>10.3f}")
    print(f"{'':<18}{'':>10}{'':>11}{'':>9}  95 % interval over rooms (bootstrap of {n_rooms} rooms): "
          f"{map50_lo:.3f}-{map50_hi:.3f}")
    for name, r in rows.items():
        c = counts[name]
        ap_txt = f"{r['ap50']:>10.3f}" if r["ap50"] >= 0 else f"{'n/a':>10}"
        p_txt = f"{r['precision']:>11.3f}" if c["tp"] + c["fp"] else f"{'n/a':>11}"  # no detections
        r_txt = f"{r['recall']:>9.3f}" if r["instances"] else f"{'n/a':>9}"
        print(f"{name:<18}{r['instances']:>10}{p_txt}{r_txt}{ap_txt}")
    print()
    fn, fp = errors["false_negatives"], errors["false_positives"]
    print("where the errors are, at the operating point:")
    print(f"  missed objects ({sum(fn.values())}): " + ", ".join(f"{k} {v}" for k, v in fn.items()))
    print(f"  false positives ({sum(fp.values())}): " + ", ".join(f"{k} {v}" for k, v in fp.items()))
    print("  wrong class, true->detected: " + ", ".join(
        f"{k} {v}" for k, v in errors["confused_true_to_detected"].items()))
    print("  recall by kind: " + ", ".join(
        f"{k} {v['recall']:.3f} ({v['objects']})" for k, v in errors["recall_by_kind"].items()
        if v["recall"] is not None))
    print("  mAP@0.5 by box area: " + ", ".join(f"{k} {v:.3f}" for k, v in map50_by_area.items()))
    print("  recall by visible fraction (of the object's unoccluded, untruncated silhouette): " + ", ".join(
        f"{k} {v['recall']:.3f} ({v['objects']})" for k, v in visibility["recall_by_visible_fraction"].items()
        if v["recall"] is not None))
    print("  mAP@0.5 with objects less visible than this also ignored (not the headline): " + ", ".join(
        f"<{k} {v:.3f}" for k, v in visibility["map50_ignoring_visible_below"].items()))
    print()
    print(f"parameters: {n_params:,}   inference per frame (letterbox + ONNX Runtime + decode + NMS): "
          f"p50 {np.percentile(ms, 50):.1f} ms, p95 {np.percentile(ms, 95):.1f} ms, mean {ms.mean():.1f} ms"
          f"   (rendering took {t_render:.0f} s)")
    if scattered is not None:
        print(f"the same rooms scattered: mAP@0.5 {scattered['map50']:.3f} "
              f"({scattered['map50_interval95_rooms']['low']:.3f}-{scattered['map50_interval95_rooms']['high']:.3f}); "
              f"{args.world} minus scattered {map50 - scattered['map50']:+.3f}")
    result = {
        "world": args.world,
        "model": detector.model_path.name,
        "model_bytes": detector.model_path.stat().st_size,
        "parameters": n_params,
        "input_px": detector.input_hw_px[1],
        "split": args.split,
        "rooms": n_rooms,
        "room_seeds": {"first": seeds[0], "last": seeds[-1], "appearance_seed": args.seed},
        "overall": overall,
        "map50_interval95_rooms": {"low": round(map50_lo, 4), "high": round(map50_hi, 4),
                                   "resamples": args.resamples},
        "per_class": rows,
        "map50_by_area": map50_by_area,
        "errors": errors,
        "visibility": visibility,
        "inference": {
            "p50_ms": round(float(np.percentile(ms, 50)), 2),
            "p95_ms": round(float(np.percentile(ms, 95)), 2),
            "mean_ms": round(float(ms.mean()), 2),
            "intra_op_threads": 1,
        },
        "load_average_1min": round(os.getloadavg()[0], 2),
        "models_dir": str(BUILTIN_MODELS_DIR),
    }
    if scattered is not None:
        result["scattered"] = scattered
    print(json.dumps(result))


if __name__ == "__main__":
    main()
