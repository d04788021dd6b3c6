"""Perception and mapping in their own process, so they never hold the service's GIL.

The service process runs the event loop: the setpoint stream, MAVLink, MQTT and the mission.
Detection, tracking, geometry and the map update are CPU-heavy Python and numpy; in a thread
of the same process they compete with the event loop for the GIL (and, on a loaded CPU, a
preempted perception thread holding the GIL stalls every thread of the process), which
showed as setpoint gaps of 130-210 ms. So the camera, the perception pipeline, the semantic
map and its checkpoints live in a child process (``spawn``):

* the child opens the frame source itself (a camera's frames never cross a process
  boundary), runs :class:`~companion.service.perception_worker.PerceptionWorker` on the
  newest frame (bounded queue, the oldest frame dropped) and saves map checkpoints;
* after every frame it sends a :class:`PerceptionUpdate` through a pipe (a
  :class:`~planner.process.WorkerProcess`, the helper the planning process uses too): counters, stage
  timings, and - at most every ``COSTMAP_PERIOD_S`` - the costmap at the flight band and the
  object list, with the capture time of the newest frame they include;
* :class:`PerceptionProcess` (async context manager, in the service) starts the child, keeps
  the latest update for the planner, the status and the freshness check, and on exit stops
  the child, which saves the map one last time; the final map is then loaded from that save.

A child that dies is started again from the last map checkpoint; meanwhile the map is stale, so
the offboard controller holds position. If it cannot be started again the service lands.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from types import TracebackType
from typing import Literal

from companion.background import TASK_STOP_TIMEOUT_S, stop_tasks
from companion.config import CompanionConfig
from companion.service.checkpoint import Checkpointer, checkpoint_path, restore_map
from companion.service.perception_worker import (
    PerceptionWorker,
    TimedPipeline,
    TimedSource,
    flight_band,
    new_object_map,
    new_semantic_map,
)
from companion.sources.base import FrameSource
from planner.process import WorkerProcess
from semmap.costmap import Costmap, ObjectFootprint, VerticalBand
from semmap.errors import MapError, PerceptionError
from semmap.grid import GridSpec
from semmap.kernels import warm_up
from semmap.semantic_map import SemanticMap

log = logging.getLogger(__name__)

#: The costmap and objects are sent to the service at most this often (the planner checks
#: its path every 0.5 s; a 400x400 costmap is ~0.5 MB).
COSTMAP_PERIOD_S = 0.2
#: The child sends an update at least this often, frames or not (it also notices a dead parent).
KEEPALIVE_S = 1.0
#: How long the child may take to start (imports, detector model, map restore).
START_TIMEOUT_S = 120.0
#: How long the child may take to stop (last frame, final map save).
STOP_TIMEOUT_S = 30.0
#: A dead child is started again this many times in a row before perception is given up.
MAX_RESTARTS = 3
#: Pause before starting a dead child again (a crash loop must not eat the CPU).
RESTART_DELAY_S = 1.0
#: The perception process's nice value relative to the service (an unprivileged process may
#: lower its own priority): the setpoint stream gets the CPU first, perception the rest.
PERCEPTION_NICE = 5


def perception_nice(cfg: CompanionConfig) -> int:
    """The perception process's nice increment: :data:`PERCEPTION_NICE`, or 0 when the SLAM runs in it
    (``service.localization: slam``): a niced thread preempted while holding the GIL it shares with
    detection and mapping stalls the SLAM, and the SLAM pose is PX4's position without GPS."""
    return 0 if cfg.service.localization == "slam" else PERCEPTION_NICE


@dataclass(frozen=True)
class PerceptionUpdate:
    """What the perception process reports after a frame (or as a keep-alive).

    Times are ``time.monotonic()`` seconds (one clock for every process on the machine).
    ``capture_mono_s``: when the newest integrated frame was read from the camera.
    ``costmap``/``objects``: the map at the flight band and its objects, or None when not
    sent with this update (they are sent at most every ``COSTMAP_PERIOD_S``);
    ``costmap_capture_mono_s`` is the capture time of the newest frame in that costmap.
    """

    #: "ready" (the first update: the child serves), "frame", "final" (the map is saved).
    kind: Literal["ready", "frame", "final"]
    restored: bool
    frames_done: int
    frames_failed: int
    frames_dropped: int
    last_frame_mono_s: float | None
    capture_mono_s: float | None
    timings_ms: dict[str, float]
    timings_summary: dict[str, dict[str, float]]
    checkpoints: int
    #: Frames skipped for want of a pose (see :mod:`companion.sources.poses`).
    frames_unposed: int = 0
    costmap: Costmap | None = None
    costmap_capture_mono_s: float | None = None
    objects: tuple[ObjectFootprint, ...] | None = None
    map_spec: GridSpec | None = None


@dataclass(frozen=True)
class _ChildSpec:
    cfg: CompanionConfig
    source: FrameSource
    object_classes: Mapping[int, str] | None
    log_level: int


def _child_main(conn: Connection, stop: Connection, spec: _ChildSpec) -> None:
    """The perception process's entry point (``spawn``)."""
    # The service decides when perception stops (SIGTERM/Ctrl-C reach the whole process group).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # When the CPU is short, the service process (setpoints, MAVLink) runs first.
    with contextlib.suppress(OSError):
        os.nice(perception_nice(spec.cfg))
    logging.basicConfig(level=spec.log_level,
                        format="%(asctime)s %(levelname)-7s %(name)s [perception]: %(message)s")
    try:
        asyncio.run(_child(spec, conn, stop))
    except Exception:
        log.exception("perception process failed")
        raise SystemExit(1) from None
    finally:
        conn.close()


def _wait_for_stop(stop: Connection, loop: asyncio.AbstractEventLoop, stopping: asyncio.Event) -> None:
    """Block until the service closes its end of the stop pipe (or dies), then set ``stopping``."""
    with contextlib.suppress(EOFError, OSError):
        stop.recv()
    with contextlib.suppress(RuntimeError):  # the child's loop has closed already
        loop.call_soon_threadsafe(stopping.set)


async def _child(spec: _ChildSpec, conn: Connection, stop: Connection) -> None:
    cfg = spec.cfg
    parent = os.getppid()
    # Compile (or load from numba's cache) the per-frame kernels before reporting ready, so
    # the first real frame does not stall for seconds while the vehicle waits for a map.
    log.info("map-update kernels ready in %.2f s", await asyncio.to_thread(warm_up))
    restored = restore_map(cfg, checkpoint_path(cfg))
    smap = restored if restored is not None else new_semantic_map(cfg)
    source = TimedSource(spec.source)
    pipeline = TimedPipeline.from_config(cfg, smap, spec.object_classes)
    pipeline.source = source
    band = flight_band(cfg)
    loop = asyncio.get_running_loop()
    frame_seen = asyncio.Event()
    stopping = asyncio.Event()
    threading.Thread(target=_wait_for_stop, args=(stop, loop, stopping), name="perception-stop",
                     daemon=True).start()

    worker = PerceptionWorker(pipeline, source, rate_hz=cfg.camera.rate_hz,
                              queue_size=cfg.service.frame_queue_size, stale_after_s=cfg.map.stale_after_s)
    ckpt = Checkpointer(smap, checkpoint_path(cfg), cfg.service.checkpoint_interval_s, pipeline.lock)

    update = functools.partial(_perception_update, pipeline, smap, band, worker, ckpt, restored is not None)

    async def send(u: PerceptionUpdate) -> None:
        await asyncio.to_thread(conn.send, u)

    async with worker, ckpt:
        worker.on_frame = frame_seen.set
        await send(update("ready", True))
        last_map_s = time.monotonic()
        sent_frames = pipeline.frames_done
        while not stopping.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(KEEPALIVE_S):
                    await frame_seen.wait()
            frame_seen.clear()
            if os.getppid() != parent:
                log.error("the service process is gone; perception stops")
                return
            now = time.monotonic()
            with_map = pipeline.frames_done != sent_frames and now - last_map_s >= COSTMAP_PERIOD_S
            u = await asyncio.to_thread(update, "frame", with_map)
            if with_map:
                last_map_s = now
                sent_frames = u.frames_done
            try:
                await send(u)
            except (BrokenPipeError, OSError):
                log.error("the service process closed the pipe; perception stops")
                return
    # The checkpointer saved the map on exit: tell the service it may load it.
    with contextlib.suppress(BrokenPipeError, OSError):
        await send(update("final", True))


def _perception_update(
    pipeline: TimedPipeline, smap: SemanticMap, band: VerticalBand, worker: PerceptionWorker, ckpt: Checkpointer,
    restored: bool, kind: Literal["ready", "frame", "final"], with_map: bool,
) -> PerceptionUpdate:
    """The child's counters and timings now; ``with_map``: with the costmap at ``band`` and the
    objects, taken under the pipeline's lock so they are one state of the map."""
    cm, cm_t, objs = None, None, None
    if with_map:
        cm_t = pipeline.capture_mono_s
        with pipeline.lock:
            cm = smap.costmap(band)
            objs = smap.objects
    return PerceptionUpdate(
        kind, restored, pipeline.frames_done, pipeline.frames_failed, worker.dropped_frames,
        pipeline.last_frame_s, pipeline.capture_mono_s, dict(pipeline.timings.latest_ms),
        pipeline.timings.summary(), ckpt.saves, pipeline.frames_unposed, cm, cm_t, objs, smap.spec)


@dataclass
class _Child:
    """One perception process as the service holds it."""

    #: The process and the service's ends of its pipes: closing the stop pipe
    #: (:meth:`~planner.process.WorkerProcess.request_stop`, or the service dying) stops it.
    proc: WorkerProcess
    reader: threading.Thread
    ready: asyncio.Event = field(default_factory=asyncio.Event)
    ended: asyncio.Event = field(default_factory=asyncio.Event)


class PerceptionProcess:
    """The perception process, seen from the service (async context manager).

    ``source`` must be picklable (it is opened in the child). ``object_classes``: the
    simulator's object id -> class for the oracle detector. ``on_frame`` is called (on the
    event loop) whenever the child reports that frames went through perception (the systemd
    watchdog's heartbeat). The map lives in the child; :meth:`costmap`, :attr:`objects` and
    :attr:`spec` give its latest state at the flight band.

    A child that dies is started again (it restores the last checkpoint), up to
    ``MAX_RESTARTS`` times in a row; after that :attr:`failed` is set and ``on_failed``
    called (the service lands). A child killed by a signal while starting is retried the
    same way; one that exits with an error while starting is not (its log says why).
    """

    def __init__(self, cfg: CompanionConfig, source: FrameSource,
                 object_classes: Mapping[int, str] | None = None) -> None:
        self.cfg = cfg
        self.source = source
        self.object_classes = dict(object_classes) if object_classes is not None else None
        self.band = flight_band(cfg)
        self.on_frame: Callable[[], None] | None = None
        #: Called on the event loop when perception is given up for good.
        self.on_failed: Callable[[], None] | None = None
        self.latest: PerceptionUpdate | None = None
        self.final_map: SemanticMap | None = None
        #: Perception processes started again after one died.
        self.restarts = 0
        #: True once a dead perception process could not be started again.
        self.failed = False
        self._costmap: Costmap | None = None
        self._objects: tuple[ObjectFootprint, ...] = ()
        self._spec: GridSpec | None = None
        #: Capture times of recent costmaps (by identity), for the frame-to-setpoint latency.
        self._capture_by_costmap: deque[tuple[Costmap, float | None]] = deque(maxlen=16)
        #: Frame capture -> costmap in the service (ms), recent values.
        self.frame_to_map_ms: deque[float] = deque(maxlen=2000)
        self._child: _Child | None = None
        self._stopping = False
        self._supervisor: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # --- lifecycle ----------------------------------------------------------------------

    async def __aenter__(self) -> PerceptionProcess:
        self._loop = asyncio.get_running_loop()
        self._stopping = False
        for attempt in range(MAX_RESTARTS + 1):
            code = await self._spawn()
            if code is None:
                break
            if code >= 0 or attempt == MAX_RESTARTS:
                raise PerceptionError(f"the perception process did not start (exit code {code}); "
                                      "see its log lines above")
            self.restarts += 1
            log.warning("the perception process was killed while starting (signal %d); starting it again", -code)
        self._supervisor = asyncio.create_task(self._supervise(), name="perception-supervisor")
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self._shutdown()
        path = checkpoint_path(self.cfg)
        if path.is_file():
            try:
                self.final_map = await asyncio.to_thread(SemanticMap.load, path, object_map=new_object_map(self.cfg))
            except MapError as exc:
                log.error("the perception process's final map %s cannot be loaded: %s", path, exc)

    async def _spawn(self) -> int | None:
        """Start a child and wait until it is ready: None when it is, else its exit code."""
        spec = _ChildSpec(self.cfg, self.source, self.object_classes, logging.getLogger().getEffectiveLevel())
        proc = WorkerProcess(_child_main, (spec,), "companion-perception", duplex=False, stop_pipe=True)
        # The child holds the only sending end: the reader gets EOF when it exits.
        await asyncio.to_thread(proc.start)
        child = _Child(proc, threading.Thread(target=lambda: None))
        child.reader = threading.Thread(target=self._read, args=(proc.conn, child), name="perception-updates",
                                        daemon=True)
        self._child = child
        child.reader.start()
        ready, ended = asyncio.ensure_future(child.ready.wait()), asyncio.ensure_future(child.ended.wait())
        try:
            await asyncio.wait({ready, ended}, timeout=START_TIMEOUT_S, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            proc.kill()  # cancelled while it starts: it ignores the SIGTERM multiprocessing's exit sends
            raise
        finally:
            ready.cancel()
            ended.cancel()
        if child.ready.is_set():
            log.info("perception process %d running", proc.pid)
            return None
        # A child that ended is exiting by itself (its exit code says how); one that never got
        # ready in time is killed.
        await self._stop_child(child, kill=not child.ended.is_set())
        return int(proc.exitcode) if proc.exitcode is not None else -int(signal.SIGKILL)

    async def _supervise(self) -> None:
        """Start a dead child again; give up (``on_failed``) after ``MAX_RESTARTS`` tries."""
        while True:
            child = self._child
            assert child is not None
            await child.ended.wait()
            await asyncio.to_thread(child.proc.join, 5.0)
            child.proc.request_stop()  # closes the dead child's stop pipe: one descriptor less per restart
            log.error("the perception process %d died (exit code %s): the map goes stale, the vehicle "
                      "holds; starting it again from the last map checkpoint", child.proc.pid, child.proc.exitcode)
            for attempt in range(1, MAX_RESTARTS + 1):
                await asyncio.sleep(RESTART_DELAY_S)
                self.restarts += 1
                code = await self._spawn()
                if code is None:
                    log.warning("perception process started again (%d restarts so far)", self.restarts)
                    break
                log.error("perception process did not start again (exit code %s; attempt %d of %d)",
                          code, attempt, MAX_RESTARTS)
            else:
                self.failed = True
                log.error("perception is gone: %d attempts to start it again failed", MAX_RESTARTS)
                if self.on_failed is not None:
                    self.on_failed()
                return

    async def _shutdown(self) -> None:
        self._stopping = True
        supervisor, self._supervisor = self._supervisor, None
        await stop_tasks([supervisor] if supervisor else [], TASK_STOP_TIMEOUT_S, "stopping the perception supervisor")
        child = self._child  # kept until it has stopped: a stop that overran its bound kills it
        if child is not None:  # one not ready yet has no newer map than the checkpoint: no wait
            await self._stop_child(child, kill=not child.ready.is_set())
        self._child = None

    async def _stop_child(self, child: _Child, *, kill: bool) -> None:
        """Stop one child (the stop pipe's close never blocks; it saves the map); ``kill``: at once."""
        proc = child.proc
        proc.request_stop()
        if kill and proc.is_alive():
            proc.kill()
        await asyncio.to_thread(proc.join, STOP_TIMEOUT_S)
        if proc.is_alive():
            log.error("perception process did not stop within %.0f s; killing it", STOP_TIMEOUT_S)
            proc.kill()
            await asyncio.to_thread(proc.join, 5.0)
        elif proc.exitcode and not kill:
            log.warning("perception process exited with code %s", proc.exitcode)
        await asyncio.to_thread(child.reader.join, 5.0)

    def _read(self, conn: Connection, child: _Child) -> None:
        """The reader thread: hand each update to the event loop."""
        loop = self._loop
        assert loop is not None
        try:
            while True:
                try:
                    u = conn.recv()
                except (EOFError, OSError):
                    break
                with contextlib.suppress(RuntimeError):  # the loop closed
                    loop.call_soon_threadsafe(self._apply, u, child)
        finally:
            conn.close()
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(child.ended.set)

    def _apply(self, u: PerceptionUpdate, child: _Child | None = None) -> None:
        prev = self.latest
        self.latest = u
        if u.map_spec is not None:
            self._spec = u.map_spec
        if u.costmap is not None:
            self._costmap = u.costmap
            self._capture_by_costmap.append((u.costmap, u.costmap_capture_mono_s))
            if u.costmap_capture_mono_s is not None:
                self.frame_to_map_ms.append(1e3 * (time.monotonic() - u.costmap_capture_mono_s))
        if u.objects is not None:
            self._objects = u.objects
        if u.kind == "ready" and child is not None:
            child.ready.set()
        # A frame skipped for want of a pose still shows the camera and perception alive.
        handled = u.frames_done + u.frames_failed + u.frames_unposed
        if self.on_frame is not None and (
                prev is None or handled != prev.frames_done + prev.frames_failed + prev.frames_unposed):
            self.on_frame()

    # --- the latest state ---------------------------------------------------------------

    def costmap(self, band: VerticalBand | None = None) -> Costmap:
        """The latest costmap at the flight band (the only band the child computes)."""
        if band is not None and band != self.band:
            raise MapError(f"the perception process maps the flight band {self.band}, not {band}")
        if self._costmap is None:
            raise MapError("no costmap from the perception process yet")
        return self._costmap

    def capture_time(self, costmap: Costmap) -> float | None:
        """The capture time (monotonic s) of the newest frame in ``costmap``, if known."""
        for cm, t in reversed(self._capture_by_costmap):
            if cm is costmap:
                return t
        return None

    @property
    def objects(self) -> tuple[ObjectFootprint, ...]:
        """The map's objects as last reported."""
        return self._objects

    @property
    def spec(self) -> GridSpec | None:
        """The map's grid as last reported (it grows with the map)."""
        return self._spec

    @property
    def restored(self) -> bool:
        return self.latest is not None and self.latest.restored

    @property
    def running(self) -> bool:
        return self._child is not None and self._child.ready.is_set() and self._child.proc.is_alive()

    @property
    def worker(self) -> WorkerProcess | None:  # the child now (for a stop's diagnostics)
        return self._child.proc if self._child is not None else None

    def is_fresh(self) -> bool:
        """True while frames keep being integrated (within ``map.stale_after_s``)."""
        u = self.latest
        if u is None or u.last_frame_mono_s is None or not self.running:
            return False
        return time.monotonic() - u.last_frame_mono_s <= self.cfg.map.stale_after_s

    def counters(self) -> dict[str, int]:
        """``{"processed", "failed", "dropped", "unposed", "checkpoints"}`` as last reported."""
        u = self.latest
        if u is None:
            return {"processed": 0, "failed": 0, "dropped": 0, "unposed": 0, "checkpoints": 0}
        return {"processed": u.frames_done, "failed": u.frames_failed, "dropped": u.frames_dropped,
                "unposed": u.frames_unposed, "checkpoints": u.checkpoints}
