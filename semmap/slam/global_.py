"""Global SLAM: the pose graph over submaps and nodes, and the background loop closer.

Every scan local SLAM inserts becomes a *node*, tied to the submaps it went into
(intra-submap constraints) and to the previous node. Every ``loop_closure_every_n_nodes``-th
node is queued for loop closure: a worker thread matches its hits against nearby finished
submaps with branch and bound, refines the hit with least squares, adds the match as a robust
constraint and, every few new constraints, re-optimises the graph. The live pipeline only
appends under a short lock and ``put_nowait``s on a bounded queue: it never waits for a
search or an optimisation (a full queue drops the node, logged).

After an optimisation the *global-from-local* correction (the latest optimised node's global
pose composed with the inverse of its local pose) carries the newest nodes, and the
``generation`` counter rises so callers can re-anchor map contents.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.config import SlamConfig
from semmap.scan import BandScan
from semmap.slam.pose2d import Pose2, compose, inverse, relative, transform_xy
from semmap.slam.pose_graph import Edge, optimize
from semmap.slam.refine import refine_pose
from semmap.slam.submaps import Submap

log = logging.getLogger(__name__)


@dataclass
class Node:
    """An inserted scan: ``local_pose`` from local SLAM, ``global_pose`` (both (3,)),
    ``points_xy_m`` (N, 2) its filtered hits (body frame), ``scan`` its rays."""

    index: int
    stamp_s: float
    local_pose: Pose2
    global_pose: Pose2
    points_xy_m: NDArray[np.float64]
    scan: BandScan
    submaps: tuple[int, ...]


@dataclass(frozen=True)
class LoopClosure:
    """A found loop closure: ``node`` seen from ``submap`` at ``relative_pose`` (3,)."""

    node: int
    submap: int
    relative_pose: tuple[float, float, float]
    score: float


class GlobalSlam:
    """Pose graph, loop-closure worker and the global-from-local correction (thread-safe)."""

    def __init__(self, cfg: SlamConfig, submaps: list[Submap], background: bool = True) -> None:
        self.cfg = cfg
        self._submaps = submaps  # shared with local SLAM (appended there, read here)
        self._lock = threading.RLock()
        self.nodes: list[Node] = []
        self.submap_global: dict[int, Pose2] = {}
        self.edges: list[tuple[str, int, str, int, Edge]] = []  # (kind_a, a, kind_b, b, edge)
        self.loop_closures: list[LoopClosure] = []
        self.global_from_local: Pose2 = np.zeros(3)
        self.generation = 0
        self.n_dropped = 0
        self._new_loops = 0
        self._listeners: list[Callable[[int], None]] = []
        self._queue: queue.Queue[int | None] = queue.Queue(maxsize=cfg.loop_closure_queue_size)
        self._background = background
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name="slam-loop-closure", daemon=True)
            self._thread.start()

    # --- live path -------------------------------------------------------------------

    def add_listener(self, callback: Callable[[int], None]) -> None:
        """``callback(generation)`` runs (on the worker thread) after poses moved."""
        self._listeners.append(callback)

    def to_global(self, local_pose: Pose2) -> Pose2:
        """A local-frame pose in the map frame with the latest correction."""
        with self._lock:
            return compose(self.global_from_local, local_pose)

    def add_node(self, stamp_s: float, local_pose: Pose2, points_xy_m: NDArray[np.float64],
                 scan: BandScan, submap_indices: tuple[int, ...]) -> Node:
        """Append a node with its intra-submap and consecutive-node constraints; queue it for
        loop closure when due (never blocks: a full queue drops it)."""
        cfg = self.cfg
        with self._lock:
            for i in submap_indices:
                if i not in self.submap_global:
                    self.submap_global[i] = compose(self.global_from_local, self._submaps[i].local_pose)
            node = Node(len(self.nodes), stamp_s, local_pose.copy(), compose(self.global_from_local, local_pose),
                        points_xy_m, scan, submap_indices)
            self.nodes.append(node)
            for i in submap_indices:
                z = relative(self._submaps[i].local_pose, local_pose)
                self.edges.append(("s", i, "n", node.index, Edge(0, 0, tuple(z), cfg.constraint_translation_weight,
                                                                 cfg.constraint_rotation_weight)))
            if node.index > 0:
                prev = self.nodes[node.index - 1]
                z = relative(prev.local_pose, local_pose)
                self.edges.append(("n", prev.index, "n", node.index, Edge(
                    0, 0, tuple(z), cfg.local_translation_weight, cfg.local_rotation_weight)))
        if node.index % cfg.loop_closure_every_n_nodes == 0:
            if self._background:
                try:
                    self._queue.put_nowait(node.index)
                except queue.Full:
                    # The worker is behind (a busy CPU): skip this node, the next ones overlap it.
                    self.n_dropped += 1
                    if self.n_dropped % 100 == 1:
                        log.warning("loop closure queue full: %d nodes not searched so far", self.n_dropped)
            else:
                self._process(node.index)
        return node

    # --- worker ----------------------------------------------------------------------

    def drain(self, timeout_s: float | None = None) -> bool:
        """Wait until every queued node has been searched (for offline runs and tests);
        returns False on timeout."""
        if not self._background:
            return True
        done = threading.Event()

        def waiter() -> None:
            self._queue.join()
            done.set()

        threading.Thread(target=waiter, daemon=True).start()
        return done.wait(timeout_s)

    def close(self) -> None:
        """Stop the worker (pending searches are abandoned)."""
        if self._thread is not None and self._thread.is_alive():
            while True:
                try:
                    self._queue.get_nowait()
                    self._queue.task_done()
                except queue.Empty:
                    break
            self._queue.put(None)
            self._thread.join(timeout=10.0)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                self._process(item)
            except Exception:  # noqa: BLE001 - the worker must survive one bad search
                log.exception("loop closure for node %s failed", item)
            finally:
                self._queue.task_done()

    def _process(self, node_index: int) -> None:
        cfg = self.cfg
        with self._lock:
            node = self.nodes[node_index]
            candidates = [(s, self.submap_global.get(s.index)) for s in self._submaps
                          if s.finished and s.index not in node.submaps]
            node_global = node.global_pose.copy()
        found = False
        for sub, sg in candidates:
            if sg is None:
                continue
            x0, y0, x1, y1 = sub.grid.spec.extent_xy_m
            centre = transform_xy(sg, np.array([[(x0 + x1) / 2.0, (y0 + y1) / 2.0]]))[0]
            if float(np.hypot(*(centre - node_global[:2]))) > cfg.loop_closure_max_distance_m:
                continue
            closure = self._match(node, sub, relative(sg, node_global))
            if closure is None:
                continue
            with self._lock:
                self.loop_closures.append(closure)
                self.edges.append(("s", sub.index, "n", node.index, Edge(
                    0, 0, closure.relative_pose, cfg.loop_translation_weight, cfg.loop_rotation_weight, robust=True)))
                self._new_loops += 1
            found = True
        if found and self._new_loops >= cfg.optimize_every_n_constraints:
            self.optimize()

    def _match(self, node: Node, sub: Submap, initial: Pose2) -> LoopClosure | None:
        cfg = self.cfg
        if len(node.points_xy_m) < cfg.min_scan_points:
            return None
        bbs = sub.branch_and_bound(cfg.branch_and_bound_depth)
        hit = bbs.match(node.points_xy_m, initial, cfg.loop_closure_linear_window_m,
                        math.radians(cfg.loop_closure_angular_window_deg), cfg.loop_closure_min_score)
        if hit is None:
            return None
        pose, score = hit
        # No prior: the branch-and-bound pose is quantised (a cell, an angular step) and must
        # not bias the constraint.
        ref = refine_pose(sub.match_grid(), node.points_xy_m, pose, occupied_space_weight=cfg.occupied_space_weight,
                          translation_weight=0.0, rotation_weight=0.0)
        lo, hi = ref.translation_eigenvalues()
        if lo < cfg.min_translation_information or lo < cfg.min_information_ratio * hi:
            return None
        log.debug("loop closure: node %d in submap %d (score %.2f)", node.index, sub.index, score)
        return LoopClosure(node.index, sub.index, (float(ref.pose[0]), float(ref.pose[1]), float(ref.pose[2])), score)

    def optimize(self) -> None:
        """Optimise the graph as it is now and re-anchor everything added meanwhile."""
        cfg = self.cfg
        with self._lock:
            self._new_loops = 0
            n_nodes = len(self.nodes)
            sub_ids = sorted(self.submap_global)
            if n_nodes == 0 or not sub_ids:
                return
            index = {("s", s): k for k, s in enumerate(sub_ids)}
            index.update({("n", i): len(sub_ids) + i for i in range(n_nodes)})
            poses = np.array([self.submap_global[s] for s in sub_ids] + [n.global_pose for n in self.nodes[:n_nodes]])
            edges = [Edge(index[(ka, a)], index[(kb, b)], e.z, e.translation_weight, e.rotation_weight, e.robust)
                     for ka, a, kb, b, e in self.edges if (ka, a) in index and (kb, b) in index]
        result = optimize(poses, edges, n_fixed=1, huber_scale=cfg.huber_scale,
                          max_iterations=cfg.optimization_iterations)
        with self._lock:
            for k, s in enumerate(sub_ids):
                self.submap_global[s] = result.poses[k]
            for i in range(n_nodes):
                self.nodes[i].global_pose = result.poses[len(sub_ids) + i]
            last = self.nodes[n_nodes - 1]
            self.global_from_local = compose(last.global_pose, inverse(last.local_pose))
            for n in self.nodes[n_nodes:]:
                n.global_pose = compose(self.global_from_local, n.local_pose)
            for s in self.submap_global:
                if ("s", s) not in index:
                    self.submap_global[s] = compose(self.global_from_local, self._submaps[s].local_pose)
            self.generation += 1
            gen = self.generation
        log.info("pose graph optimised (generation %d): cost %.4g -> %.4g", gen, result.cost_initial, result.cost_final)
        for cb in list(self._listeners):
            cb(gen)
