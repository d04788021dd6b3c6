"""``companion map SEQUENCE --out DIR``: build a semantic map offline from a recording."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TextIO

from companion.config import load_config


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "map", help="build a semantic map offline from a recorded RGB-D folder",
        description="Run detection (a detector model or a detections file), tracking, object "
        "geometry, the object map and the occupancy grid over a recorded folder (TUM layout, "
        "color/ + depth/ + pose.txt, or N.png + N_depth.png) and write map.pgm/.yaml, "
        "costmap.pgm/.yaml, map.png, objects.json, semantic_map.npz and the effective config "
        "into --out. The recording needs camera poses.",
    )
    p.add_argument("sequence", help="recorded folder")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--detections", default=None,
                   help="detections JSON ({'frames': {file name: [{class, score, xyxy}]}}) "
                   "instead of the config's detector model")
    p.add_argument("--no-tracker", action="store_true",
                   help="one track per box (sparse keyframes; the object map re-associates)")
    p.add_argument("--no-floor", action="store_true",
                   help="the recording's world is already z-up with the floor at z = 0")
    p.add_argument("--geo-origin", default=None, metavar="LAT,LON",
                   help="WGS-84 position of the map origin: also write objects.geojson")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=_run)


class ProgressBar:
    """A one-line progress bar on stderr (redrawn in place on a terminal, else every 10 %)."""

    def __init__(self, label: str, width: int = 30, stream: TextIO | None = None) -> None:
        self.label = label
        self.width = width
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.monotonic()
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self._last_decile = -1

    def __call__(self, done: int, total: int) -> None:
        frac = done / max(1, total)
        elapsed = time.monotonic() - self.t0
        eta = elapsed / frac - elapsed if frac > 0 else 0.0
        filled = int(round(frac * self.width))
        line = (f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {done}/{total} "
                f"{elapsed:5.1f} s elapsed, {eta:5.1f} s left")
        if self.tty:
            self.stream.write("\r" + line + ("\n" if done >= total else ""))
            self.stream.flush()
            return
        decile = int(frac * 10)
        if decile != self._last_decile or done >= total:
            self._last_decile = decile
            self.stream.write(line + "\n")
            self.stream.flush()


def _run(args: argparse.Namespace) -> int:
    from companion.offline_map import OfflineMapOptions, build_offline_map, parse_lat_lon

    cfg = load_config(args.config)
    opts = OfflineMapOptions(
        detections_path=Path(args.detections) if args.detections else None,
        use_tracker=not args.no_tracker,
        align_floor=not args.no_floor,
        geo_origin_lat_lon_deg=parse_lat_lon(args.geo_origin) if args.geo_origin else None,
        max_frames=args.max_frames,
    )
    progress = None if args.no_progress else ProgressBar("mapping")
    result = build_offline_map(args.sequence, args.out, cfg, opts, progress)
    smap = result.semantic_map
    print(f"map: {result.frames_used} frames ({result.frames_skipped} skipped), "
          f"{len(smap.objects)} objects, grid {smap.spec.cols}x{smap.spec.rows} cells "
          f"at {smap.spec.resolution_m:g} m")
    for o in smap.objects:
        c = o.polygon_xy_m.mean(axis=0)
        print(f"  #{o.object_id:<3} {o.class_name:<18} existence {o.existence:.2f}  "
              f"centre ({c[0]:+.2f}, {c[1]:+.2f}) m  height {o.z_max_m:.2f} m")
    print(f"outputs in {Path(args.out)}:")
    for role, path in result.files.items():
        print(f"  {role}: {path}")
    return 0
