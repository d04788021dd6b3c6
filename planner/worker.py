"""Planning in a separate, persistent process, so the caller never stalls on OMPL's GIL.

OMPL's ``solve`` holds the GIL for its whole budget; run in the service's process it would
freeze the setpoint stream and the MAVLink link. :class:`PlanningService` keeps one worker
process (``spawn`` context: no inherited threads or sockets) that owns a
:class:`~planner.planner.Planner`. The worker caches the fields of the last map version it
received: the client sends a costmap only when its version changed, and the worker applies it
as a windowed update, so replanning after a small change is cheap.

Requests and replies are the message dataclasses below, over a
:class:`~planner.process.WorkerProcess` pipe. Requests are synchronous (one at a time); an asyncio caller runs :meth:`PlanningService.plan`
in a thread (``asyncio.to_thread``), which waits on a pipe without holding the GIL. A request
that exceeds its deadline kills the worker (the only way to stop a running ``solve``) and
returns a ``TIMEOUT`` result; the next request starts a fresh worker. :meth:`cancel` does the
same from another thread.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from planner.config import PlannerConfig
from planner.process import Ready, Stop, WorkerProcess
from planner.types import PlanResult, PlanStatus
from semmap.costmap import Costmap
from semmap.errors import PlanningError

if TYPE_CHECKING:
    from planner.planner import Planner

log = logging.getLogger(__name__)


XY = tuple[float, ...]


@dataclass(frozen=True)
class SetMap:
    """Adopt this costmap as map ``version`` (a windowed update when the grid is unchanged)."""

    version: int
    costmap: Costmap


@dataclass(frozen=True)
class MapApplied:
    version: int
    prepare_s: float


@dataclass(frozen=True)
class PlanRequest:
    req_id: int
    start_xy_m: XY
    goal_xy_m: XY
    time_limit_s: float
    snap_goal: bool | None


@dataclass(frozen=True)
class CheckPath:
    """Is the (K, 2) map-frame polyline free on the current map."""

    req_id: int
    path_xy_m: NDArray[np.float64]


@dataclass(frozen=True)
class EscapeRequest:
    """The nearest point to ``xy_m`` where the vehicle fits with ``extra_m`` to spare."""

    req_id: int
    xy_m: XY
    extra_m: float


@dataclass(frozen=True)
class Reply:
    req_id: int
    value: object


@dataclass(frozen=True)
class Failed:
    """A request the worker could not answer (it keeps serving); ``req_id`` None for a map."""

    req_id: int | None
    message: str


def _answer(planner: Planner, msg: object) -> MapApplied | Reply:
    if isinstance(msg, SetMap):
        planner.set_map(msg.costmap, msg.version)
        return MapApplied(msg.version, planner.last_prepare_s)
    if isinstance(msg, PlanRequest):
        return Reply(msg.req_id, planner.plan(msg.start_xy_m, msg.goal_xy_m, msg.time_limit_s, msg.snap_goal))
    if isinstance(msg, CheckPath):
        return Reply(msg.req_id, bool(planner.path_still_valid(msg.path_xy_m)))
    if isinstance(msg, EscapeRequest):
        return Reply(msg.req_id, planner.escape_point(np.asarray(msg.xy_m, dtype=np.float64), msg.extra_m))
    raise PlanningError(f"unknown request {type(msg).__name__}")


def _worker_main(conn: Connection, config: PlannerConfig) -> None:
    """Worker loop: answer each request on the pipe until :class:`Stop` or the pipe closes."""
    from planner.planner import Planner  # imported in the child: OMPL loads here

    planner = Planner(config)
    conn.send(Ready())
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if isinstance(msg, Stop):
            return
        try:
            conn.send(_answer(planner, msg))
        except Exception as exc:  # noqa: BLE001 - report every failure to the client, keep serving
            conn.send(Failed(getattr(msg, "req_id", None), f"{type(exc).__name__}: {exc}"))


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
        self._proc: WorkerProcess | None = None
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
            log.warning("planning worker pid %s died (%s); starting a new one",
                        self._proc.pid, self._proc.exit_reason())
            self._abandon()
        try:
            self._start_once()
        except PlanningError as exc:
            if not str(exc).startswith("planning worker killed"):
                raise
            log.warning("%s; starting it once more", exc)
            self._start_once()

    def _start_once(self) -> None:
        worker = WorkerProcess(_worker_main, (self.config,), "planner-worker")
        worker.start()
        try:
            ready = worker.recv(time.monotonic() + self.start_timeout_s)
        except TimeoutError:
            worker.kill()
            worker.join(1.0)
            worker.close()
            raise PlanningError(f"planning worker did not start within {self.start_timeout_s} s") from None
        except EOFError as exc:
            worker.join(1.0)
            worker.close()
            raise PlanningError(f"planning worker {worker.exit_reason()} while starting") from exc
        if not isinstance(ready, Ready):
            worker.stop(1.0)
            raise PlanningError(f"planning worker sent {ready!r} instead of Ready")
        self._proc, self._worker_version = worker, None
        self.starts += 1
        log.info("planning worker started (pid %s)", worker.pid)

    def close(self) -> None:
        """Stop the worker process."""
        worker, self._proc = self._proc, None
        self._worker_version = None
        if worker is not None:
            worker.stop(2.0)

    def cancel(self) -> None:
        """Abort the running request (it returns ``TIMEOUT``); safe from another thread."""
        worker = self._proc
        if worker is not None and worker.is_alive():
            log.warning("cancelling planning request: killing worker pid %s", worker.pid)
            worker.kill()

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def worker(self) -> WorkerProcess | None:
        """The worker process now (None when none runs), for a stop's diagnostics."""
        return self._proc

    # --- requests -------------------------------------------------------------------

    def _abandon(self) -> None:
        worker, self._proc = self._proc, None
        self._worker_version = None
        if worker is not None:
            worker.kill()
            worker.join(1.0)
            worker.close()

    def _call(self, costmap: Costmap, map_version: int, deadline_mono_s: float,
              request: Callable[[int], object]) -> object:
        """Send ``costmap`` unless the worker holds ``map_version``, then ``request(req_id)``;
        returns the value of its :class:`Reply`. Raises :class:`TimeoutError` past the deadline
        and :class:`EOFError`/:class:`OSError` when the worker died (either way the worker is
        dropped, the next request starts a new one), :class:`PlanningError` when it failed."""
        with self._lock:
            self.start()
            worker = self._proc
            assert worker is not None
            try:
                if self._worker_version != map_version:
                    worker.send(SetMap(int(map_version), costmap))
                    self.maps_sent += 1
                    applied = worker.recv(deadline_mono_s)
                    if not isinstance(applied, MapApplied):
                        self._worker_version = None
                        why = applied.message if isinstance(applied, Failed) else repr(applied)
                        raise PlanningError(f"planning worker rejected map version {map_version}: {why}")
                    self._worker_version = int(map_version)
                self._next_id += 1
                req_id = self._next_id
                worker.send(request(req_id))
                while True:
                    reply = worker.recv(deadline_mono_s)
                    if isinstance(reply, Failed):
                        raise PlanningError(f"planning request rejected: {reply.message}")
                    if isinstance(reply, Reply) and reply.req_id == req_id:
                        return reply.value
            except TimeoutError:
                self._abandon()
                raise
            except (EOFError, OSError) as exc:
                worker.join(1.0)
                log.warning("planning worker pid %s died (%s, %s); a new one starts with the next request",
                            worker.pid, type(exc).__name__, worker.exit_reason())
                self._abandon()
                raise

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
        start = _xy(start_xy_m)
        goal = _xy(goal_xy_m)

        def request(req_id: int) -> PlanRequest:
            # The budget is the whole request's: a new map's preparation spends part of it
            # (the planner still always returns its first path).
            return PlanRequest(req_id, start, goal, max(0.0, limit - (time.monotonic() - t0)), snap_goal)

        try:
            result = self._call(costmap, map_version, t0 + wait, request)
        except TimeoutError:
            return PlanResult.failure(
                PlanStatus.TIMEOUT, f"planning did not finish within {wait:.2f} s; worker restarted",
                time.monotonic() - t0, map_version,
            )
        except (EOFError, OSError) as exc:
            return PlanResult.failure(
                PlanStatus.TIMEOUT, f"planning worker stopped ({type(exc).__name__}); it will be restarted",
                time.monotonic() - t0, map_version,
            )
        assert isinstance(result, PlanResult)
        return result

    def path_free(self, costmap: Costmap, map_version: int, path_xy_m: NDArray[np.floating],
                  timeout_s: float = 5.0) -> bool | None:
        """Whether the (K, 2) map-frame polyline is free on ``costmap`` (identified by
        ``map_version``), judged by the worker's configuration space exactly as the planner
        judges its own paths; so the caller's process never builds one. The costmap is
        transferred only if the worker does not hold this version yet. Returns None when the
        worker did not answer within ``timeout_s`` (it is restarted, as for :meth:`plan`)."""
        path = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
        try:
            free = self._call(costmap, map_version, time.monotonic() + float(timeout_s),
                              lambda req_id: CheckPath(req_id, path))
        except (TimeoutError, EOFError, OSError):
            return None
        return bool(free)

    def escape_point(self, costmap: Costmap, map_version: int, xy_m: Sequence[float] | NDArray[np.floating],
                     extra_m: float = 0.05, timeout_s: float = 5.0) -> NDArray[np.float64] | None:
        """The nearest map-frame point to ``xy_m`` where the vehicle fits with ``extra_m`` to
        spare on ``costmap``, from the worker's configuration space; None when there is none
        or the worker did not answer within ``timeout_s`` (it is restarted)."""
        xy = _xy(xy_m)
        try:
            point = self._call(costmap, map_version, time.monotonic() + float(timeout_s),
                               lambda req_id: EscapeRequest(req_id, xy, float(extra_m)))
        except (TimeoutError, EOFError, OSError):
            return None
        return None if point is None else np.asarray(point, dtype=np.float64)


def _xy(value: Sequence[float] | NDArray[np.floating]) -> XY:
    """Plain floats for the pipe; the planner validates the shape (two finite numbers)."""
    return tuple(float(v) for v in np.asarray(value, dtype=np.float64).reshape(-1))
