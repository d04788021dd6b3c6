"""``companion dataset``: render a YOLO-format detector dataset from the simulated world."""

from __future__ import annotations

import argparse
import json
import time

from companion.config import load_config
from companion.sim.dataset import ROOM_SEED_START, DatasetSpec, write_dataset
from semmap.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "dataset",
        help="render detector training images and YOLO labels from simulated rooms",
        description="Render images of generated rooms with YOLO labels of the config's classes "
        "(Ultralytics layout: images/<split>, labels/<split>, data.yaml). Train and held-out "
        "splits use disjoint room seeds.",
    )
    p.add_argument("--out", required=True, help="dataset folder (created)")
    p.add_argument("--split", default="train", choices=sorted(ROOM_SEED_START))
    p.add_argument("--rooms", type=int, default=10, help="rooms to render (default 10)")
    p.add_argument("--room-start", type=int, default=0,
                   help="index of the first room of the split (to render a split in parallel parts)")
    p.add_argument("--images-per-room", type=int, default=20)
    p.add_argument("--seed", type=int, default=0, help="appearance and camera-pose seed")
    p.add_argument("--min-visible-px", type=int, default=120,
                   help="objects with fewer visible pixels are not labelled (default 120)")
    p.add_argument("--motion-blur-fraction", type=float, default=0.3)
    p.add_argument("--aim-class-balanced", action="store_true",
                   help="aim at a uniformly drawn class of the room, then one of its objects, so "
                   "rare classes get as many aimed views as chairs (training data)")
    p.add_argument("--aim-clutter", type=float, default=0.0, metavar="FRAC",
                   help="fraction of the aimed images aimed at clutter instead of furniture: hard "
                   "negatives (training data; default 0)")
    p.add_argument("--class-weights", default="",
                   help="relative class frequencies of the rooms, e.g. conference_table=2,sofa=1.5 "
                   "(classes left out keep the world's defaults; training data)")
    p.add_argument("--layout", choices=("realistic", "scattered"), default=None,
                   help="room layout (default: the config's sim.layout)")
    p.add_argument("--config", default=None, help="config file for classes and camera intrinsics")
    p.set_defaults(func=_run)


def _class_weights(text: str, class_names: list[str]) -> tuple[tuple[str, float], ...]:
    """``"name=w,name=w"`` as ``((name, w), ...)``; a clear error names the bad item."""
    out = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or name not in class_names:
            raise ConfigError(f"--class-weights: {item!r} is not <class>=<weight> with a class of {class_names}")
        try:
            out.append((name, float(value)))
        except ValueError:
            raise ConfigError(f"--class-weights: weight of {name!r} is not a number ({value!r})") from None
    return tuple(out)


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    names = [c.name for c in cfg.classes]
    spec = DatasetSpec(
        split=args.split, n_rooms=args.rooms, images_per_room=args.images_per_room, seed=args.seed,
        class_names=tuple(names), intrinsics=cfg.camera.intrinsics(),
        min_visible_px=args.min_visible_px, motion_blur_fraction=args.motion_blur_fraction,
        aim_class_balanced=args.aim_class_balanced, aim_clutter_fraction=args.aim_clutter,
        class_weights=_class_weights(args.class_weights, names),
        layout=args.layout or cfg.sim.layout,
    )
    t0 = time.perf_counter()
    counts = write_dataset(spec, args.out, room_start=args.room_start)
    counts["seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(counts))
    return 0
