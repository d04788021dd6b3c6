"""Map checkpoints: the semantic map saved periodically (atomic writes) and restored on start."""

from __future__ import annotations

import asyncio
import logging
import threading
from pathlib import Path
from types import TracebackType

from companion.config import CompanionConfig
from companion.service.perception_worker import new_object_map
from semmap.errors import MapError
from semmap.semantic_map import SemanticMap

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "semantic_map.npz"


def checkpoint_path(cfg: CompanionConfig) -> Path:
    """Where the service keeps its map: ``service.map_dir/semantic_map.npz``."""
    return Path(cfg.service.map_dir) / CHECKPOINT_NAME


def restore_map(cfg: CompanionConfig, path: Path) -> SemanticMap | None:
    """The checkpointed map at ``path`` with a fresh object map, or None when there is none.

    A damaged checkpoint is logged and set aside (renamed ``*.bad``) so the service starts
    with an empty map instead of failing at every restart.
    """
    if not path.is_file():
        return None
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
