"""Planning in a separate, persistent process, so the caller never stalls on OMPL's GIL.

OMPL's ``solve`` holds the GIL for its whole budget; run in the service's process it would
freeze the setpoint stream and the MAVLink link. :class:`PlanningService` keeps one worker
process (``spawn`` context: no inherited threads or sockets) that owns a
:class:`~planner.planner.Planner`. The worker caches the fields of the last map version it
received: the client sends a costmap only when its version changed, and the worker applies it
as a windowed update, so replanning after a small change is cheap.

Requests are synchronous (one at a time); an asyncio caller runs :meth:`PlanningService.plan`
in a thread (``asyncio.to_thread``), which waits on a pipe without holding the GIL. A request
that exceeds its deadline kills the worker (the only way to stop a running ``solve``) and
returns a ``TIMEOUT`` result; the next request starts a fresh worker. :meth:`cancel` does the
same from another thread.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner.config import PlannerConfig
from planner.types import PlanResult, PlanStatus
from semmap.costmap import Costmap
from semmap.errors import PlanningError

log = logging.getLogger(__name__)


def _worker_main(conn: Connection, config: PlannerConfig) -> None:
    """Worker loop: ``("map", version, costmap)``, ``("plan", id, start, goal, limit, snap)`` and
    ``("check", id, path)`` (is the (K, 2) path free on the current map)."""
    from planner.planner import Planner  # imported in the child: OMPL loads here

    planner = Planner(config)
    conn.send(("ready",))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        kind = msg[0]
        if kind == "stop":
            return
        try:
            if kind == "map":
                _, version, costmap = msg
                planner.set_map(costmap, version)
                conn.send(("map_ok", version, planner.last_prepare_s))
            elif kind == "plan":
                _, req_id, start, goal, limit, snap = msg
                conn.send(("result", req_id, planner.plan(start, goal, limit, snap)))
            elif kind == "check":
                _, req_id, path = msg
                conn.send(("result", req_id, bool(planner.path_still_valid(np.asarray(path, dtype=np.float64)))))
            else:
                conn.send(("error", None, f"unknown request {kind!r}"))
        except Exception as exc:  # noqa: BLE001 - report every failure to the client, keep serving
            conn.send(("error", msg[1] if kind in ("plan", "check") else None, f"{type(exc).__name__}: {exc}"))


class PlanningService:
    """A persistent planning process; use as a context manager or call :meth:`close`.

    ``timeout_slack_s``: a request may take its time budget plus this (map transfer and
    preparation, process start) before it is abandoned as ``TIMEOUT``.
    """

    def __init__(self, config: PlannerConfig, timeout_slack_s: float = 5.0,
                 start_timeout_s: float = 60.0) -> None:
        self.config = config
        self.timeout_slack_s = timeout_slack_s
        self.start_timeout_s = start_timeout_s
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._conn: Connection | None = None
        self._worker_version: int | None = None
        self._next_id = 0
        self._lock = threading.Lock()
        #: How many costmaps were sent to a worker (a cached version is not sent again).
        self.maps_sent = 0
        #: How many worker processes were started (restarts after timeouts count).
        self.starts = 0

    # --- lifecycle ------------------------------------------------------------------

    def __enter__(self) -> "PlanningService":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Start the worker process if it is not running (blocks until it is ready). A worker
        killed by a signal while starting is started once more."""
        if self._proc is not None:
            if self._proc.is_alive():
                return
            log.warning("planning worker pid %d died (exit code %s); starting a new one",
                        self._proc.pid, self._proc.exitcode)
            self._abandon()
        try:
            self._start_once()
        except PlanningError as exc:
            if not str(exc).startswith("planning worker killed"):
                raise
            log.warning("%s; starting it once more", exc)
            self._start_once()

    def _start_once(self) -> None:
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(target=_worker_main, args=(child, self.config),
                                 name="planner-worker", daemon=True)
        proc.start()
        child.close()
        if not parent.poll(self.start_timeout_s):
            proc.kill()
            proc.join(1.0)
            raise PlanningError(f"planning worker did not start within {self.start_timeout_s} s")
        try:
            ready = parent.recv()
        except EOFError as exc:
            proc.join(1.0)
            code = proc.exitcode
            what = f"killed by signal {-code}" if code is not None and code < 0 else f"exited with code {code}"
            raise PlanningError(f"planning worker {what} while starting") from exc
        if ready != ("ready",):
            raise PlanningError(f"planning worker sent {ready!r} instead of ready")
        self._proc, self._conn, self._worker_version = proc, parent, None
        self.starts += 1
        log.info("planning worker started (pid %d)", proc.pid)

    def close(self) -> None:
        """Stop the worker process."""
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self._worker_version = None
        if conn is not None:
            try:
                conn.send(("stop",))
            except (OSError, ValueError):
                pass
        if proc is not None:
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        if conn is not None:
            conn.close()

    def cancel(self) -> None:
        """Abort the running request (it returns ``TIMEOUT``); safe from another thread."""
        proc = self._proc
        if proc is not None and proc.is_alive():
            log.warning("cancelling planning request: killing worker pid %d", proc.pid)
            proc.kill()

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    # --- requests -------------------------------------------------------------------

    def _recv(self, deadline: float) -> Any:
        conn = self._conn
        assert conn is not None
        remaining = deadline - time.monotonic()
        if remaining <= 0.0 or not conn.poll(remaining):
            raise TimeoutError
        return conn.recv()

    def _warn_dead(self, exc: BaseException) -> None:
        proc = self._proc
        if proc is not None:
            proc.join(1.0)
        log.warning("planning worker pid %s died (%s, exit code %s); a new one starts with the next request",
                    proc.pid if proc is not None else "?", type(exc).__name__,
                    proc.exitcode if proc is not None else "?")

    def _abandon(self) -> None:
        proc = self._proc
        self._proc = None
        if proc is not None:
            proc.kill()
            proc.join(1.0)
        if self._conn is not None:
            self._conn.close()
        self._conn = None
        self._worker_version = None

    def plan(
        self,
        costmap: Costmap,
        map_version: int,
        start_xy_m: Sequence[float] | NDArray[np.floating],
        goal_xy_m: Sequence[float] | NDArray[np.floating],
        time_limit_s: float | None = None,
        snap_goal: bool | None = None,
        timeout_s: float | None = None,
    ) -> PlanResult:
        """Plan on ``costmap`` (identified by ``map_version``) in the worker process.

        The costmap is transferred only if the worker does not hold this version yet;
        ``time_limit_s`` (default: config) bounds the whole request, that transfer and the
        map's preparation included: the planner gets what is left (at least its first path
        is always computed). ``timeout_s`` (default: the time budget plus
        ``timeout_slack_s``) bounds the whole call; past it the worker is killed and a
        ``TIMEOUT`` result returned. Raises
        :class:`PlanningError` for invalid requests (the worker keeps running) or if the
        worker cannot be started.
        """
        limit = self.config.time_limit_s if time_limit_s is None else float(time_limit_s)
        wait = limit + self.timeout_slack_s if timeout_s is None else float(timeout_s)
        t0 = time.monotonic()
        deadline = t0 + wait
        start = tuple(float(v) for v in np.asarray(start_xy_m, dtype=np.float64).reshape(-1))
        goal = tuple(float(v) for v in np.asarray(goal_xy_m, dtype=np.float64).reshape(-1))
        with self._lock:
            self.start()
            conn = self._conn
            assert conn is not None
            try:
                if self._worker_version != map_version:
                    conn.send(("map", int(map_version), costmap))
                    self.maps_sent += 1
                    reply = self._recv(deadline)
                    if reply[0] == "error":
                        self._worker_version = None
                        raise PlanningError(f"planning worker rejected map version {map_version}: {reply[2]}")
                    self._worker_version = int(map_version)
                self._next_id += 1
                req_id = self._next_id
                # The budget is the whole request's: a new map's preparation spends part of
                # it (the planner still always returns its first path).
                budget = max(0.0, limit - (time.monotonic() - t0))
                conn.send(("plan", req_id, start, goal, budget, snap_goal))
                while True:
                    reply = self._recv(deadline)
                    if reply[1] == req_id or reply[0] == "error":
                        break
            except TimeoutError:
                self._abandon()
                return PlanResult.failure(
                    PlanStatus.TIMEOUT, f"planning did not finish within {wait:.2f} s; worker restarted",
                    time.monotonic() - t0, map_version,
                )
            except (EOFError, OSError, BrokenPipeError) as exc:
                self._warn_dead(exc)
                self._abandon()
                return PlanResult.failure(
                    PlanStatus.TIMEOUT, f"planning worker stopped ({type(exc).__name__}); it will be restarted",
                    time.monotonic() - t0, map_version,
                )
        if reply[0] == "error":
            raise PlanningError(f"planning request rejected: {reply[2]}")
        result: PlanResult = reply[2]
        return result

    def path_free(self, costmap: Costmap, map_version: int, path_xy_m: NDArray[np.floating],
                  timeout_s: float = 5.0) -> bool | None:
        """Whether the (K, 2) map-frame polyline is free on ``costmap`` (identified by
        ``map_version``), judged by the worker's configuration space exactly as the planner
        judges its own paths; so the caller's process never builds one. The costmap is
        transferred only if the worker does not hold this version yet. Returns None when the
        worker did not answer within ``timeout_s`` (it is restarted, as for :meth:`plan`)."""
        path = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
        deadline = time.monotonic() + float(timeout_s)
        with self._lock:
            self.start()
            conn = self._conn
            assert conn is not None
            try:
                if self._worker_version != map_version:
                    conn.send(("map", int(map_version), costmap))
                    self.maps_sent += 1
                    reply = self._recv(deadline)
                    if reply[0] == "error":
                        self._worker_version = None
                        raise PlanningError(f"planning worker rejected map version {map_version}: {reply[2]}")
                    self._worker_version = int(map_version)
                self._next_id += 1
                req_id = self._next_id
                conn.send(("check", req_id, path))
                while True:
                    reply = self._recv(deadline)
                    if reply[1] == req_id or reply[0] == "error":
                        break
            except TimeoutError:
                self._abandon()
                return None
            except (EOFError, OSError, BrokenPipeError) as exc:
                self._warn_dead(exc)
                self._abandon()
                return None
        if reply[0] == "error":
            raise PlanningError(f"path check rejected: {reply[2]}")
        return bool(reply[2])
