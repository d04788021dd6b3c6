"""Train the shipped furniture detector (YOLOv8n from scratch) and export it to ONNX.

Runs in the training venv (the ``train`` extra: Ultralytics and a CPU build of torch), not
in the runtime venv; it imports nothing from this project, so the runtime never needs torch.

Steps (each can be run alone):

1. Data (runtime venv; disjoint room seeds per split, see ``companion/sim/dataset.py``)::

       companion dataset --out /tmp/furn --split train   --rooms 160 --images-per-room 15 --seed 0
       companion dataset --out /tmp/furn --split heldout --rooms 20  --images-per-room 15 --seed 1

2. Train (``YOLO_OFFLINE=1``; nothing is downloaded: the architecture comes from the
   ``yolov8n.yaml`` Ultralytics ships, weights start random, plots and the AMP check, which
   would fetch a font and ``yolov8n.pt``, are off)::

       YOLO_OFFLINE=1 .venv-train/bin/python tools/train_detector.py train --data /tmp/furn \\
           --out /tmp/furn-runs --time-hours 1.3

3. Export the best checkpoint to ONNX (static 1x3x320x320, opset 17) and copy it into
   ``semmap/models/``, with the training summary beside it::

       YOLO_OFFLINE=1 .venv-train/bin/python tools/train_detector.py export \\
           --run /tmp/furn-runs/furniture

The held-out figures of the shipped model come from ``python bench/detector.py`` (our runtime,
COCO evaluator), not from Ultralytics' validator.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
MODELS_DIR = REPO / "semmap" / "models"
MODEL_NAME = "furniture_yolov8n_320"
#: Our classes in CompanionConfig().classes order: the ONNX metadata's ``names`` must match.
CLASS_NAMES = ("chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk")


def _val_list(data_dir: Path, n_val: int, out_dir: Path) -> Path:
    """A data.yaml using all train images and the first ``n_val`` held-out images for the
    per-epoch validation (the full held-out set is for ``bench/detector.py``)."""
    import yaml

    heldout = sorted((data_dir / "images" / "heldout").glob("*.jpg"))
    if not heldout:
        sys.exit(f"{data_dir}/images/heldout has no images: generate the held-out split first")
    step = max(1, len(heldout) // max(1, n_val))
    out_dir.mkdir(parents=True, exist_ok=True)
    val_txt = out_dir / "val_subset.txt"
    val_txt.write_text("".join(f"{p}\n" for p in heldout[::step][:n_val]))
    cfg = {
        "path": str(data_dir.resolve()),
        "train": "images/train",
        "val": str(val_txt),
        "names": dict(enumerate(CLASS_NAMES)),
    }
    path = out_dir / "data_train.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def train(args: argparse.Namespace) -> None:
    from ultralytics import YOLO

    data = _val_list(Path(args.data), args.val_images, Path(args.out))
    settings: dict[str, Any] = {
        "data": str(data),
        "imgsz": args.imgsz,
        "batch": args.batch,
        # One optimizer step per batch (Ultralytics accumulates to 64 images by default):
        # a short CPU budget needs the steps.
        "nbs": args.batch,
        "epochs": args.epochs,
        "device": "cpu",
        "workers": 2,
        "cache": "ram",
        "optimizer": "AdamW",
        "lr0": args.lr0,
        "lrf": 0.05,
        "cos_lr": True,
        # No warmup: Ultralytics warms up for at least 100 iterations, a large share of a CPU
        # budget of a few hundred; AdamW from scratch is stable at this lr without it.
        "warmup_epochs": args.warmup_epochs,
        "close_mosaic": args.close_mosaic,
        "mosaic": 1.0,
        "fliplr": 0.5,
        "degrees": 5.0,
        "scale": 0.5,
        "pretrained": False,
        "amp": False,
        "plots": False,
        "project": str(Path(args.out).resolve()),
        "name": args.name,
        "exist_ok": True,
        "seed": 0,
        "patience": 1000,
        "verbose": True,
    }
    if args.time_hours:
        # Ultralytics fits the epoch count (and the LR schedule) to this wall-clock budget.
        settings["time"] = args.time_hours
    # --weights continues from an earlier run's checkpoint (its weights only: a fresh optimizer
    # and LR schedule fitted to this run's budget), so a budget can be spent in several sittings.
    # Ultralytics only loads a checkpoint's weights when `pretrained` names it; with
    # pretrained=False it rebuilds the architecture from scratch even from a .pt.
    model = YOLO(args.weights) if args.weights else YOLO("yolov8n.yaml")
    if args.weights:
        settings["pretrained"] = str(args.weights)
    t0 = time.time()
    model.train(**settings)
    summary = {"settings": settings, "train_seconds": round(time.time() - t0, 1),
               "ultralytics_architecture": "yolov8n.yaml",
               "initial_weights": args.weights, "torch_threads": _torch_threads()}
    (Path(args.out) / args.name / "train_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))


def _torch_threads() -> int:
    import torch

    return int(torch.get_num_threads())


def export(args: argparse.Namespace) -> None:
    import onnx
    from ultralytics import YOLO

    run = Path(args.run)
    weights = run / "weights" / ("best.pt" if args.best else "last.pt")
    model = YOLO(str(weights))
    names = [model.names[i] for i in sorted(model.names)]
    if tuple(names) != CLASS_NAMES:
        sys.exit(f"{weights}: class names {names} are not {list(CLASS_NAMES)}")
    onnx_path = Path(model.export(format="onnx", imgsz=args.imgsz, opset=args.opset, dynamic=False,
                                  simplify=args.simplify, half=False, batch=1))
    proto = onnx.load(str(onnx_path))
    meta = {p.key: p.value for p in proto.metadata_props}
    dst = MODELS_DIR / f"{MODEL_NAME}.onnx"
    MODELS_DIR.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(onnx_path, dst)
    summary_src = run / "train_summary.json"
    summary = json.loads(summary_src.read_text()) if summary_src.exists() else {}
    summary.update({
        "weights": weights.name,
        "onnx_bytes": dst.stat().st_size,
        "opset": args.opset,
        "imgsz": args.imgsz,
        "input": [d.dim_value for d in proto.graph.input[0].type.tensor_type.shape.dim],
        "metadata_names": meta.get("names"),
    })
    results = run / "results.csv"
    if results.exists():
        summary["results_csv_tail"] = results.read_text().strip().splitlines()[-3:]
    (MODELS_DIR / f"{MODEL_NAME}.train.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps({"onnx": str(dst), "bytes": dst.stat().st_size, "names": meta.get("names")}))


def main() -> None:
    os.environ.setdefault("YOLO_OFFLINE", "1")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train YOLOv8n from scratch on a dataset folder")
    t.add_argument("--data", required=True, help="folder written by `companion dataset`")
    t.add_argument("--out", default="/tmp/furn-runs")
    t.add_argument("--imgsz", type=int, default=320)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--epochs", type=int, default=30)
    t.add_argument("--time-hours", type=float, default=None,
                   help="wall-clock budget; overrides --epochs (Ultralytics' `time`)")
    t.add_argument("--weights", default=None,
                   help="start from this checkpoint (e.g. an earlier run's last.pt), not from scratch")
    t.add_argument("--name", default="furniture", help="run folder name under --out")
    t.add_argument("--lr0", type=float, default=0.002)
    t.add_argument("--close-mosaic", type=int, default=1)
    t.add_argument("--warmup-epochs", type=float, default=0.0)
    t.add_argument("--val-images", type=int, default=100,
                   help="held-out images validated after each epoch")
    t.set_defaults(func=train)
    e = sub.add_parser("export", help="export a run's checkpoint to semmap/models/")
    e.add_argument("--run", required=True, help="the run folder (…/furniture)")
    e.add_argument("--imgsz", type=int, default=320)
    e.add_argument("--opset", type=int, default=17)
    e.add_argument("--simplify", action="store_true", help="onnxslim (must be installed)")
    e.add_argument("--last", dest="best", action="store_false", help="export last.pt, not best.pt")
    e.set_defaults(func=export)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
