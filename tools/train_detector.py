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

3. Export the best checkpoint to ONNX (static 1x3xSxS at the training ``--imgsz`` S, opset
   17) and copy it into ``semmap/models/`` as ``furniture_yolov8n_S.onnx`` (replacing a model
   at another size), with the training summary beside it::

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
#: Shipped as ``furniture_yolov8n_<imgsz>.onnx``: the name states the architecture and input
#: size, and ``builtin:furniture`` resolves the single ``furniture_*.onnx`` in the folder.
MODEL_STEM = "furniture_yolov8n"


def shipped_onnx() -> Path:
    """The one shipped ``furniture_yolov8n_*.onnx`` (the default for ``from-onnx``)."""
    found = sorted(MODELS_DIR.glob(f"{MODEL_STEM}_*.onnx"))
    if len(found) != 1:
        sys.exit(f"{MODELS_DIR}: expected one {MODEL_STEM}_*.onnx, found {[p.name for p in found]}")
    return found[0]


#: Our classes in CompanionConfig().classes order: the ONNX metadata's ``names`` must match.
CLASS_NAMES = ("chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk")


def _val_list(data_dir: Path, n_val: int, out_dir: Path) -> Path:
    """A data.yaml using all train images and ``n_val`` images of the ``val`` split (rooms of
    their own) for the per-epoch validation that picks ``best.pt``. The held-out rooms are only
    for ``bench/detector.py``: choosing the epoch on them would let the reported figure pick
    its own model."""
    import yaml

    val = sorted((data_dir / "images" / "val").glob("*.jpg"))
    if not val:
        sys.exit(f"{data_dir}/images/val has no images: generate the val split first "
                 f"(companion dataset --out {data_dir} --split val ...)")
    step = max(1, len(val) // max(1, n_val))
    out_dir.mkdir(parents=True, exist_ok=True)
    val_txt = out_dir / "val_subset.txt"
    val_txt.write_text("".join(f"{p}\n" for p in val[::step][:n_val]))
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

    _use_all_cores(args.threads)
    if args.bf16:
        _bf16_training()
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
        "optimizer": args.optimizer,
        "lr0": args.lr0,
        "lrf": 0.05,
        "cos_lr": True,
        # No warmup: Ultralytics warms up for at least 100 iterations, a large share of a CPU
        # budget of a few hundred; AdamW from scratch is stable at this lr without it.
        "warmup_epochs": args.warmup_epochs,
        "close_mosaic": args.close_mosaic,
        "mosaic": args.mosaic,
        "fliplr": 0.5,
        "degrees": args.degrees,
        "scale": args.scale,
        "translate": args.translate,
        "cls": args.cls,
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
               "initial_weights": args.weights, "torch_threads": _torch_threads(),
               "bf16_autocast": bool(args.bf16)}
    (Path(args.out) / args.name / "train_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))


def _bf16_training() -> None:
    """Train the network's forward pass in bfloat16 autocast, channels-last, on the CPU.

    Ultralytics only offers mixed precision on CUDA (``amp`` is forced off on the CPU). On a
    CPU with AMX or AVX-512 BF16 (this machine's Xeon has both), bf16 autocast plus
    channels-last memory runs YOLOv8n's forward and backward at batch 16, 320 px, in 0.52 s
    instead of 0.91 s. Weights, optimizer state and the loss stay float32: the patch casts the
    network's outputs back to float32 before Ultralytics' loss sees them, and validation
    (``model.training`` false) runs in float32 as before.
    """
    import torch
    from ultralytics.nn import tasks

    original = tasks.BaseModel._predict_once

    def to_float(out: Any) -> Any:
        if torch.is_tensor(out):
            return out.float()
        if isinstance(out, dict):
            return {k: to_float(v) for k, v in out.items()}
        if isinstance(out, (list, tuple)):
            return type(out)(to_float(v) for v in out)
        return out

    def predict_once(self: Any, x: Any, *a: Any, **kw: Any) -> Any:
        if not self.training:
            return original(self, x, *a, **kw)
        if not getattr(self, "_channels_last", False):
            self.to(memory_format=torch.channels_last)
            self._channels_last = True
        x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = original(self, x, *a, **kw)
        return to_float(out)

    tasks.BaseModel._predict_once = predict_once


def _use_all_cores(threads: int) -> None:
    """Ultralytics sets torch to ``os.cpu_count() - 1`` threads for CPU training (its
    ``NUM_THREADS``, sized to leave a core for data-loader workers), and then runs the data
    loading in the main process anyway (``workers = 0`` on CPU): on a 2-core machine that trains
    on one core. Make its ``select_device`` use ``threads``."""
    from ultralytics.utils import torch_utils

    torch_utils.NUM_THREADS = threads


def from_onnx(args: argparse.Namespace) -> None:
    """Rebuild a trainable Ultralytics checkpoint from a shipped ONNX model.

    The ONNX graph holds YOLOv8's convolutions with their batch norms fused in (weight ``W``,
    bias ``b``), under the parameter names of the PyTorch model. The unfused model needs each
    batch norm back: one forward pass over real images measures every convolution's raw output
    ``y = W * x`` per channel (mean ``m``, variance ``v``), and the batch norm is set to
    ``running_mean = m``, ``running_var = v``, ``weight = sqrt(v + eps)``, ``bias = m + b``, so
    that it computes ``y + b``, the fused layer, exactly in eval mode and on batches like these
    in train mode. A later run continues from the shipped weights with ``--weights``.
    """
    import cv2
    import numpy as np
    import onnx
    import torch
    from onnx import numpy_helper
    from ultralytics import __version__
    from ultralytics.data.augment import LetterBox
    from ultralytics.nn.modules.conv import Conv
    from ultralytics.nn.tasks import DetectionModel

    if args.onnx is None:
        args.onnx = shipped_onnx()
    proto = onnx.load(str(args.onnx))
    if args.imgsz is None:  # the size the network was exported at
        args.imgsz = int(proto.graph.input[0].type.tensor_type.shape.dim[-1].dim_value)
    fused = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in proto.graph.initializer}
    model = DetectionModel("yolov8n.yaml", nc=len(CLASS_NAMES), verbose=False)
    model.names = dict(enumerate(CLASS_NAMES))
    params = dict(model.named_parameters())
    used: set[str] = set()
    pending: dict[torch.nn.BatchNorm2d, torch.Tensor] = {}
    with torch.no_grad():
        for name, module in model.named_modules():
            if isinstance(module, Conv):
                w, b = fused[f"{name}.conv.weight"], fused[f"{name}.conv.bias"]
                module.conv.weight.copy_(w)
                pending[module.bn] = b
                used.update({f"{name}.conv.weight", f"{name}.conv.bias"})
        for pname, p in params.items():
            if pname in fused and pname not in used:  # the head's plain Conv2d layers, DFL
                if tuple(p.shape) != tuple(fused[pname].shape):
                    sys.exit(f"{args.onnx}: {pname} is {tuple(fused[pname].shape)}, model has {tuple(p.shape)}")
                p.copy_(fused[pname])
                used.add(pname)
    missing = [n for n in params if n not in used and not n.endswith((".bn.weight", ".bn.bias"))]
    if missing:
        sys.exit(f"{args.onnx}: no weights for {missing[:5]} ...")

    def calibrate(bn: torch.nn.BatchNorm2d, inputs: tuple[torch.Tensor, ...]) -> None:
        y = inputs[0]
        m, v = y.mean(dim=(0, 2, 3)), y.var(dim=(0, 2, 3), unbiased=False)
        bn.running_mean.copy_(m)
        bn.running_var.copy_(v)
        bn.weight.copy_(torch.sqrt(v + bn.eps))
        bn.bias.copy_(m + pending[bn])

    images = sorted(Path(args.images).glob("*.jpg"))[: args.calib_images]
    if not images:
        sys.exit(f"{args.images}: no .jpg images to calibrate the batch norms on")
    # Ultralytics' own letterbox (centred, grey 114), as its validator feeds the model.
    letterbox = LetterBox((args.imgsz, args.imgsz), auto=False)
    batch = np.stack([letterbox(image=cv2.imread(str(p)))[:, :, ::-1] for p in images])
    x = torch.from_numpy(batch).permute(0, 3, 1, 2).float() / 255.0
    hooks = [bn.register_forward_pre_hook(calibrate) for bn in pending]
    model.eval()
    with torch.no_grad():
        model(x)
    for h in hooks:
        h.remove()
    # Check: the rebuilt model in eval mode reproduces the ONNX outputs.
    import onnxruntime as ort

    sess = ort.InferenceSession(str(args.onnx), providers=["CPUExecutionProvider"])
    ref = np.concatenate([sess.run(None, {sess.get_inputs()[0].name: x[i:i + 1].numpy()})[0]
                          for i in range(4)])
    with torch.no_grad():
        out = model(x[:4])[0].numpy()
    err = float(np.abs(out - ref).max())
    print(json.dumps({"onnx": str(args.onnx), "max_abs_output_difference": err,
                      "calibration_images": len(images)}))
    if err > 1e-2 * max(1.0, float(np.abs(ref).max())):
        sys.exit(f"rebuilt model differs from {args.onnx} by {err}")
    ckpt = {"model": model.half(), "ema": None, "updates": None, "optimizer": None, "epoch": -1,
            "train_args": {"imgsz": args.imgsz, "task": "detect"}, "version": __version__,
            "from_onnx": str(args.onnx)}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, args.out)


def _torch_threads() -> int:
    import torch

    return int(torch.get_num_threads())


def export(args: argparse.Namespace) -> None:
    import onnx
    from ultralytics import YOLO

    run = Path(args.run)
    weights = run / "weights" / ("best.pt" if args.best else "last.pt")
    model = YOLO(str(weights))
    if args.imgsz is None:  # export at the size the run trained at
        args.imgsz = int(model.ckpt.get("train_args", {}).get("imgsz", 320))
    names = [model.names[i] for i in sorted(model.names)]
    if tuple(names) != CLASS_NAMES:
        sys.exit(f"{weights}: class names {names} are not {list(CLASS_NAMES)}")
    onnx_path = Path(model.export(format="onnx", imgsz=args.imgsz, opset=args.opset, dynamic=False,
                                  simplify=args.simplify, half=False, batch=1))
    proto = onnx.load(str(onnx_path))
    meta = {p.key: p.value for p in proto.metadata_props}
    name = f"{MODEL_STEM}_{args.imgsz}"
    dst = MODELS_DIR / f"{name}.onnx"
    MODELS_DIR.mkdir(parents=True, exist_ok=True)
    # A model at another input size is replaced, not kept beside: two variants would make
    # ``builtin:furniture`` ambiguous.
    for old in MODELS_DIR.glob(f"{MODEL_STEM}_*"):
        if not old.name.startswith(f"{name}."):
            old.unlink()
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
    (MODELS_DIR / f"{name}.train.json").write_text(json.dumps(summary, indent=2) + "\n")
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
    t.add_argument("--optimizer", default="AdamW", choices=("AdamW", "SGD"),
                   help="AdamW trains from scratch; SGD (momentum 0.937) continues a trained "
                   "checkpoint without AdamW's full-size first steps shaking it")
    t.add_argument("--bf16", action="store_true",
                   help="bfloat16 autocast and channels-last for the training forward pass (a CPU "
                   "with AMX or AVX-512 BF16: about 1.7x faster); weights and loss stay float32")
    t.add_argument("--close-mosaic", type=int, default=1)
    t.add_argument("--warmup-epochs", type=float, default=0.0)
    # Geometric augmentation. Ultralytics' defaults (mosaic, +-50 % scale) suit a model that
    # must generalise from few real photographs; here every image comes from one camera model
    # and fresh rooms are free, and where an object stands in the frame relative to the horizon
    # (the camera's tilt) is what tells a coffee table from a desk from a conference table.
    t.add_argument("--mosaic", type=float, default=1.0, help="mosaic probability (0 = off)")
    t.add_argument("--scale", type=float, default=0.5, help="random zoom gain (+-)")
    t.add_argument("--translate", type=float, default=0.1, help="random shift (fraction of size)")
    t.add_argument("--degrees", type=float, default=5.0, help="random rotation (+-deg)")
    t.add_argument("--cls", type=float, default=0.5,
                   help="classification loss gain (Ultralytics' default 0.5; box 7.5, dfl 1.5)")
    t.add_argument("--val-images", type=int, default=100,
                   help="val-split images validated after each epoch (picks best.pt)")
    t.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                   help="torch threads (default: all cores; Ultralytics alone leaves one idle)")
    t.set_defaults(func=train)
    o = sub.add_parser("from-onnx", help="rebuild a trainable checkpoint from a shipped ONNX model")
    o.add_argument("--onnx", default=None, help="default: the shipped furniture_yolov8n_*.onnx")
    o.add_argument("--images", required=True, help="folder of .jpg images for the batch-norm statistics")
    o.add_argument("--calib-images", type=int, default=64)
    o.add_argument("--imgsz", type=int, default=None, help="default: the ONNX model's input size")
    o.add_argument("--out", default="/tmp/furn-runs/from_onnx.pt")
    o.set_defaults(func=from_onnx)
    e = sub.add_parser("export", help="export a run's checkpoint to semmap/models/")
    e.add_argument("--run", required=True, help="the run folder (…/furniture)")
    e.add_argument("--imgsz", type=int, default=None, help="default: the run's training size")
    e.add_argument("--opset", type=int, default=17)
    e.add_argument("--simplify", action="store_true", help="onnxslim (must be installed)")
    e.add_argument("--last", dest="best", action="store_false", help="export last.pt, not best.pt")
    e.set_defaults(func=export)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
