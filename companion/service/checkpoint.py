"""Map checkpoints: the semantic map saved periodically (atomic writes) and restored on start."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import zipfile
from pathlib import Path
from types import TracebackType

import numpy as np

from companion.config import CompanionConfig
from companion.service.perception_worker import new_object_map
from semmap.errors import ConfigError, MapError
from semmap.grid import GridSpec
from semmap.semantic_map import SemanticMap

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "semantic_map.npz"


def checkpoint_path(cfg: CompanionConfig) -> Path:
    """Where the service keeps its map: ``service.map_dir/semantic_map.npz``."""
    return Path(cfg.service.map_dir) / CHECKPOINT_NAME


def _checkpoint_grid(path: Path) -> GridSpec | None:
    """The grid a checkpoint holds, read from its header; None if it cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(z["meta"].tobytes().decode("utf-8"))
        g = meta["grid"]
        ox, oy = (float(v) for v in g["origin_xy_m"])
        rows, cols = (int(v) for v in g["shape_rc"])
        return GridSpec(float(g["resolution_m"]), (ox, oy), (rows, cols))
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError):
        return None  # a damaged checkpoint is set aside by restore_map


def checkpoint_mismatch(cfg: CompanionConfig, path: Path) -> str | None:
    """Why the checkpoint at ``path`` cannot continue under ``cfg.map``, naming both; None if
    it can (or there is none). A growing grid may have grown past the configured extent, but
    on the same cells; a fixed-size one must be the configured grid exactly."""
    if not path.is_file():
        return None
    have = _checkpoint_grid(path)
    if have is None:
        return None
    m = cfg.map
    want = GridSpec.covering(m.origin_xy_m[0], m.origin_xy_m[1], m.origin_xy_m[0] + m.width_m,
                             m.origin_xy_m[1] + m.height_m, m.resolution_m)
    res = m.resolution_m
    tol = 1e-6
    if abs(have.resolution_m - res) > tol:
        ok = False
    elif m.fixed_size:
        ok = have.shape_rc == want.shape_rc and all(
            abs(a - b) < tol for a, b in zip(have.origin_xy_m, want.origin_xy_m, strict=True))
    else:
        hx0, hy0, hx1, hy1 = have.extent_xy_m
        wx0, wy0, wx1, wy1 = want.extent_xy_m
        steps = [(w - h) / res for w, h in zip(want.origin_xy_m, have.origin_xy_m, strict=True)]
        ok = (hx0 <= wx0 + tol and hy0 <= wy0 + tol and hx1 >= wx1 - tol and hy1 >= wy1 - tol
              and all(abs(s - round(s)) < 1e-4 for s in steps))
    if ok:
        return None

    def describe(g: GridSpec) -> str:
        x0, y0, x1, y1 = g.extent_xy_m
        return (f"resolution_m {g.resolution_m:g}, origin_xy_m [{x0:g}, {y0:g}], "
                f"{x1 - x0:g} x {y1 - y0:g} m")

    return (f"service.map_dir: the map checkpoint {path} ({describe(have)}) does not match "
            f"the configured map ({describe(want)}{', fixed_size' if m.fixed_size else ''}): "
            "set map.* to the checkpoint's, or move the checkpoint away to start a new map")


def restore_map(cfg: CompanionConfig, path: Path) -> SemanticMap | None:
    """The checkpointed map at ``path`` with a fresh object map, or None when there is none.

    A damaged checkpoint is logged and set aside (renamed ``*.bad``) so the service starts
    with an empty map instead of failing at every restart. One made with other map settings
    (:func:`checkpoint_mismatch`) is a :class:`ConfigError`: the map is kept, not replaced.
    """
    if not path.is_file():
        return None
    mismatch = checkpoint_mismatch(cfg, path)
    if mismatch is not None:
        raise ConfigError(mismatch)
    try:
        smap = SemanticMap.load(path, object_map=new_object_map(cfg))
    except MapError as exc:
        bad = path.with_suffix(path.suffix + ".bad")
        log.error("map checkpoint %s unusable (%s); moved to %s, starting with an empty map", path, exc, bad)
        path.replace(bad)
        return None
    log.info("restored the map from %s: %d objects", path, len(smap.objects))
    return smap


class Checkpointer:
    """Saves ``smap`` to ``path`` every ``interval_s`` and once more on exit (async context
    manager). ``lock`` guards the map against the perception thread while saving."""

    def __init__(self, smap: SemanticMap, path: Path, interval_s: float, lock: threading.Lock) -> None:
        self.smap = smap
        self.path = path
        self.interval_s = interval_s
        self.lock = lock
        self.saves = 0
        self._task: asyncio.Task[None] | None = None

    def save_now(self) -> Path:
        """Save the map atomically (blocking); returns the path."""
        with self.lock:
            self.smap.save(self.path)
        self.saves += 1
        return self.path

    async def __aenter__(self) -> Checkpointer:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._task = asyncio.create_task(self._run(), name="map-checkpoint")
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
        try:
            await asyncio.to_thread(self.save_now)
            log.info("map saved to %s", self.path)
        except MapError as exc:
            log.error("final map save failed: %s", exc)

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.interval_s)
            try:
                await asyncio.to_thread(self.save_now)
            except MapError as exc:
                log.error("map checkpoint failed (will retry): %s", exc)
