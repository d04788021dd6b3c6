"""Submaps: small probability grids built from a run of consecutive scans.

As in Cartographer, two submaps are active at a time: every inserted scan goes into both, the
older one is the scan matcher's target, and when the newer one has received half of
``scans_per_submap`` scans the older one is full: it is *finished* (frozen, never changed
again; loop closure matches against it) and a new submap is started. So each submap holds
``scans_per_submap`` scans and consecutive submaps overlap by half.

A submap's frame is the local SLAM frame shifted to the position of its first scan (no
rotation): its grid is axis-aligned in the local frame, and its *global* pose is what the
pose graph optimises.
"""

from __future__ import annotations

import threading

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from semmap.errors import MapError
from semmap.grid import GridSpec
from semmap.occupancy import ProbabilityGrid, ProbabilityTables
from semmap.scan import BandScan
from semmap.slam.correlative import BranchAndBoundMatcher, MatchGrid
from semmap.slam.pose2d import Pose2, pose2, relative, transform_scan


class Submap:
    """One submap: ``index``, ``local_pose`` (3,) of its frame in the local SLAM frame,
    ``grid`` (a growing :class:`ProbabilityGrid` in the submap frame), scan count and state."""

    def __init__(self, index: int, origin_local_xy_m: tuple[float, float], resolution_m: float,
                 tables: ProbabilityTables, blur_sigma_cells: float = 1.0,
                 live_blur_sigma_cells: float = 0.75) -> None:
        self.index = index
        self.local_pose = pose2(origin_local_xy_m[0], origin_local_xy_m[1], 0.0)
        half = 2.0
        spec = GridSpec.covering(-half, -half, half, half, resolution_m)
        self.grid = ProbabilityGrid(spec, tables, grow_chunk_m=2.0)
        self.n_scans = 0
        #: Obstacle points inserted so far (what a scan can be matched against).
        self.n_hits = 0
        self.finished = False
        self.blur_sigma_cells = float(blur_sigma_cells)
        self.live_blur_sigma_cells = float(live_blur_sigma_cells)
        self._hits: list[np.ndarray] = []  # (K, 2) hits of each scan, submap frame
        self._match: MatchGrid | None = None
        self._live: MatchGrid | None = None
        self._seen: NDArray[np.bool_] | None = None
        self._bbs: BranchAndBoundMatcher | None = None
        self._lock = threading.Lock()

    def insert(self, scan: BandScan, pose_local: Pose2) -> None:
        """Insert a scan whose body sits at ``pose_local`` (local SLAM frame)."""
        if self.finished:
            raise MapError(f"submap {self.index} is finished; it takes no more scans")
        rays = transform_scan(relative(self.local_pose, pose_local), scan)
        self.grid.insert_scan(rays.origin_xy_m, rays.near_xy_m, rays.far_xy_m, rays.hit_xy_m,
                              rays.is_hit, rays.valid)
        self._hits.append(rays.hits_xy_m)
        self.n_scans += 1
        self.n_hits += len(rays.hits_xy_m)
        self._match = None
        self._live = None
        self._seen = None

    def finish(self) -> None:
        """Freeze the submap (loop closure may now match against it)."""
        self.finished = True
        self._live = None  # only the live scan matcher uses these two
        self._seen = None

    def match_grid(self) -> MatchGrid:
        """The grid loop closure scores against (cached until the next insertion): the
        likelihood field of the inserted hits (:meth:`MatchGrid.from_hits`) with sigma
        ``blur_sigma_cells`` cells, over the probability grid's extent."""
        if self._match is None:
            self._match = self._field(self.blur_sigma_cells)
        return self._match

    def live_match_grid(self) -> MatchGrid:
        """The grid the live scan matcher scores against: the same field with sigma
        ``live_blur_sigma_cells``. Narrower, because a turning scan's leading edge lies beyond
        the known end of a wall, and the field's tail there pulls it back (the heading lags
        every turn); loop closure searches wide windows from far-off guesses and keeps the
        wider basin."""
        if self._live is None:
            self._live = self._field(self.live_blur_sigma_cells)
        return self._live

    def _field(self, sigma_cells: float) -> MatchGrid:
        hits = np.concatenate(self._hits) if self._hits else np.zeros((0, 2))
        return MatchGrid.from_hits(hits, self.grid.spec, sigma_cells * self.grid.spec.resolution_m)

    def seen(self, xy_m: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(N,) True where the (N, 2) submap-frame points lie on a cell a ray has crossed or
        ended in, or on a cell beside one: range noise puts a wall's hits up to a cell behind
        it, where no ray reached. Cached until the next insertion."""
        spec = self.grid.spec
        if self._seen is None:
            self._seen = ndimage.binary_dilation(self.grid.known)
        rc = spec.cell_of(xy_m)
        inside = spec.contains_rc(rc)
        out = np.zeros(len(rc), dtype=bool)
        out[inside] = self._seen[rc[inside, 0], rc[inside, 1]]
        return out

    def branch_and_bound(self, depth: int) -> BranchAndBoundMatcher:
        """The loop-closure matcher of a finished submap (built once, thread-safe)."""
        if not self.finished:
            raise MapError(f"submap {self.index} is still active; loop closure needs finished submaps")
        with self._lock:
            if self._bbs is None:
                self._bbs = BranchAndBoundMatcher(self.match_grid(), depth)
            return self._bbs


class ActiveSubmaps:
    """The two active submaps and every submap made so far (``all``, by index)."""

    def __init__(self, scans_per_submap: int, resolution_m: float, tables: ProbabilityTables,
                 blur_sigma_cells: float = 1.0, live_blur_sigma_cells: float = 0.75) -> None:
        if scans_per_submap < 2:
            raise MapError(f"scans_per_submap must be >= 2 (got {scans_per_submap})")
        self.scans_per_submap = int(scans_per_submap)
        self.resolution_m = float(resolution_m)
        self.tables = tables
        self.blur_sigma_cells = blur_sigma_cells
        self.live_blur_sigma_cells = live_blur_sigma_cells
        self.all: list[Submap] = []
        self.active: list[Submap] = []

    @property
    def matching_submap(self) -> Submap | None:
        """The older active submap (the scan matcher's target), None before the first scan."""
        return self.active[0] if self.active else None

    def insert(self, scan: BandScan, pose_local: Pose2) -> tuple[list[Submap], list[Submap]]:
        """Insert into the active submaps, starting/finishing submaps as needed. Returns
        ``(inserted_into, newly_finished)``."""
        if not self.active:
            self._start(pose_local)
        finished: list[Submap] = []
        for s in self.active:
            s.insert(scan, pose_local)
        inserted = list(self.active)
        if self.active[0].n_scans >= self.scans_per_submap:
            old = self.active.pop(0)
            old.finish()
            finished.append(old)
        if self.active[-1].n_scans >= self.scans_per_submap // 2 and len(self.active) < 2:
            self._start(pose_local)
        if not self.active:
            self._start(pose_local)
        return inserted, finished

    def _start(self, pose_local: Pose2) -> None:
        s = Submap(len(self.all), (float(pose_local[0]), float(pose_local[1])), self.resolution_m,
                   self.tables, self.blur_sigma_cells, self.live_blur_sigma_cells)
        self.all.append(s)
        self.active.append(s)

