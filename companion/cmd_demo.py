"""``companion demo --out DIR``: the simulated world, a scripted flight, pictures and a summary."""

from __future__ import annotations

import argparse

from companion.config import load_config


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "demo", help="fly a scripted route through the seeded simulated room and write pictures",
        description="Generate the seeded room of the config, fly from one doorway to the other, "
        "render RGB-D frames and write frame pictures, the ground-truth map, the effective config "
        "and summary.json into --out.",
    )
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--seed", type=int, default=None, help="room seed (overrides sim.seed)")
    p.add_argument("--frames", type=int, default=40, help="frames to render along the flight (default 40)")
    p.add_argument("--pictures", type=int, default=4, help="frames to write as pictures (default 4)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from companion.sim.demo import run_demo  # the renderer needs the 'sim' extra

    cfg = load_config(args.config)
    if args.seed is not None:
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": args.seed})})
    result = run_demo(cfg, args.out, n_frames=args.frames, n_pictures=args.pictures)
    s = result.summary
    print(f"demo: room seed {s['seed']}, {len(s['objects'])} objects, "
          f"{s['frames']['rendered']} frames rendered, flight {s['flight']['duration_s']} s")
    print(f"outputs in {result.out_dir}:")
    for role in ("ground_truth_map", "summary", "config"):
        print(f"  {role}: {result.files[role]}")
    frames_dir = result.out_dir / "frames"
    print(f"  frame pictures: {frames_dir} ({sum(1 for k in result.files if k.startswith('frame_'))} files)")
    return 0
