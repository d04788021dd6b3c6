"""What the PX4 SITL benchmarks share: their common options, the config they fly, the rooms and
PX4's start-up (``bench/px4_sitl.py``, ``bench/px4_gps_denied.py``)."""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any, TypeVar

from companion.config import CompanionConfig, load_config
from companion.sim.demo_e2e import feasible_seed
from companion.sim.px4_sitl import Px4Sitl, Px4SitlError, sitl_available

#: PX4's readiness on a loaded machine: the EKF can take minutes (README: 15-70 s idle).
READY_TIMEOUT_S = 240.0

SitlT = TypeVar("SitlT", bound=Px4Sitl)


def add_common_args(ap: argparse.ArgumentParser, *, rooms: int, quick_help: str) -> None:
    """The options every PX4 SITL benchmark takes."""
    ap.add_argument("--rooms", type=int, default=rooms, help=f"seeded rooms to fly (default {rooms})")
    ap.add_argument("--seed", type=int, default=0, help="first room seed (default 0)")
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--detector", choices=("onnx", "oracle"), default="onnx",
                    help="onnx (default, as the demo): the shipped model; oracle: the simulator's")
    ap.add_argument("--out", default=None, help="keep the flights' outputs here (default: a temporary folder)")
    ap.add_argument("--timeout", type=float, default=240.0, help="give a room's mission up after this many seconds")


def prepare(args: argparse.Namespace, bench: str, log: logging.Logger) -> tuple[CompanionConfig, Path] | None:
    """Logging, the shipped config with ``--detector``, and the output folder; None (after
    saying why on stderr) when PX4 SITL cannot run here."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    ok, why = sitl_available()
    if not ok:
        print(f"{bench} bench: {why}", file=sys.stderr)
        return None
    cfg = load_config(None)
    cfg = cfg.model_copy(update={"detector": cfg.detector.model_copy(update={
        "kind": args.detector, "model_path": cfg.detector.model_path or "builtin:furniture"})})
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix=f"bench-{bench.replace('_', '-')}-"))
    return cfg, out


def with_seed(cfg: Any, seed: int) -> Any:
    """``cfg`` flying the room of ``seed``."""
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": seed})})


def room_seeds(cfg: Any, start: int, n: int) -> list[int]:
    """The first ``n`` seeds from ``start`` whose room has a feasible crossing (each once)."""
    seeds: list[int] = []
    s = start
    while len(seeds) < n:
        got = feasible_seed(with_seed(cfg, s)).sim.seed
        if got not in seeds:
            seeds.append(got)
        s = got + 1
    return seeds


def start_sitl(cfg: Any, log: logging.Logger, sitl_type: type[SitlT] = Px4Sitl,  # type: ignore[assignment]
               **kw: Any) -> SitlT:
    """A started PX4 SITL at the config's home (``kw`` to its constructor); a second try when
    the first is not ready in time (on a loaded machine PX4's EKF can take minutes to converge)."""
    s = cfg.sim
    for attempt in (1, 2):
        sitl = sitl_type(home_lat_lon_alt=(s.home_lat_deg, s.home_lon_deg, s.home_alt_m),
                         ready_timeout_s=READY_TIMEOUT_S, **kw)
        try:
            sitl.start()
            return sitl
        except Px4SitlError as exc:
            if attempt == 2:
                raise
            log.warning("PX4 SITL did not start (%s); trying once more", str(exc).splitlines()[0])
    raise AssertionError("unreachable")
