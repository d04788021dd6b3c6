"""Simulated flights through generated rooms for the tracking benchmark.

A flight alternates yaw turns at a fixed rate (60 deg/s by default: the drone turns to face its
next waypoint, and looks around when it gets there) with straight legs at walking speed between
random waypoints that keep clear of furniture and walls. Each frame is rendered by
:mod:`companion.sim.render`, detected by the oracle detector (noise, misses, false positives) and
tracked. Identity switches are counted against the renderer's instance ids.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from companion.config import CompanionConfig
from companion.sim.groundtruth import clearance_m, path_collides
from companion.sim.render import RoomRenderer
from companion.sim.world import Room
from semmap.detection.oracle import OracleDetector
from semmap.frames import pose_from_xyz_rpy, wrap_angle_rad
from semmap.tracking.matching import iou_matrix
from semmap.types import CameraIntrinsics, Detection, Track

#: A tracker as the flight sees it: this frame's detections and image -> confirmed tracks.
TrackFn = Callable[[list[Detection], NDArray[np.uint8]], list[Track]]

VEHICLE_RADIUS_M = 0.35
VEHICLE_HEIGHT_M = 0.3


def scripted_flight(
    room: Room,
    duration_s: float,
    rate_hz: float = 15.0,
    yaw_rate_dps: float = 60.0,
    speed_mps: float = 0.5,
    altitude_m: float = 1.0,
    seed: int = 0,
) -> list[tuple[float, float, float]]:
    """Body poses ``(x_m, y_m, yaw_rad)`` (map frame) at ``rate_hz`` for ``duration_s``."""
    rng = np.random.default_rng(seed)
    xs = np.arange(0.4, room.width_m - 0.4, 0.2)
    ys = np.arange(0.4, room.depth_m - 0.4, 0.2)
    grid = np.array([(x, y, altitude_m) for x in xs for y in ys])
    free = grid[clearance_m(room, grid, VEHICLE_HEIGHT_M) > VEHICLE_RADIUS_M + 0.15]
    if len(free) == 0:
        raise ValueError(f"room {room.seed} has no free flying space")
    pos = free[int(rng.integers(len(free)))][:2].copy()
    yaw = float(rng.uniform(-math.pi, math.pi))
    dt = 1.0 / rate_hz
    n = int(round(duration_s * rate_hz))
    poses: list[tuple[float, float, float]] = []
    turn_step = math.radians(yaw_rate_dps) * dt

    def turn_by(delta: float) -> None:
        nonlocal yaw
        for _ in range(int(abs(delta) / turn_step)):
            yaw += math.copysign(turn_step, delta)
            poses.append((pos[0], pos[1], yaw))

    while len(poses) < n:
        # Look around: 90..270 deg at the full yaw rate, either way.
        turn_by(float(rng.choice([-1.0, 1.0]) * rng.uniform(math.pi / 2, 1.5 * math.pi)))
        for _ in range(50):
            goal = free[int(rng.integers(len(free)))][:2]
            dist = float(np.linalg.norm(goal - pos))
            seg = np.array([[pos[0], pos[1], altitude_m], [goal[0], goal[1], altitude_m]])
            if 1.0 < dist < 4.0 and not path_collides(room, seg, VEHICLE_RADIUS_M, VEHICLE_HEIGHT_M):
                break
        else:
            continue
        heading = math.atan2(goal[1] - pos[1], goal[0] - pos[0])
        turn_by(wrap_angle_rad(heading - yaw))
        steps = int(dist / (speed_mps * dt))
        start = pos.copy()
        for k in range(1, steps + 1):
            pos = start + (goal - start) * (k / steps)
            poses.append((pos[0], pos[1], yaw))
    return poses[:n]


@dataclass
class SwitchCount:
    """Identity switches of one flight.

    ``continuous``: the object's matched track id changed while it stayed in view (gaps no
    longer than the tracker's lost buffer): the tracker's fault. ``reentry``: it changed after
    the object was out of view longer than the buffer (a new track is expected then).
    """

    frames: int = 0
    continuous: int = 0
    reentry: int = 0
    matched: int = 0
    gt_boxes: int = 0
    events: list[tuple[int, int, int, int]] = field(default_factory=list)

    @property
    def per_100_frames(self) -> float:
        return 100.0 * self.continuous / max(self.frames, 1)


class SwitchCounter:
    """Counts identity switches: GT objects matched to tracks by IoU >= ``min_iou`` each frame."""

    def __init__(self, gap_frames: int, min_iou: float = 0.5) -> None:
        self.gap_frames = gap_frames
        self.min_iou = min_iou
        self.count = SwitchCount()
        self._last: dict[int, tuple[int, int]] = {}  # object id -> (track id, frame)

    def add(self, frame_index: int, gt: dict[int, tuple[float, float, float, float]], tracks: Sequence[Track]) -> None:
        """One frame: ground-truth boxes by object id and the tracker's output."""
        c = self.count
        c.frames += 1
        c.gt_boxes += len(gt)
        if not gt or not tracks:
            return
        oids = list(gt)
        iou = iou_matrix(np.array([gt[o] for o in oids]), np.array([t.xyxy_px for t in tracks]))
        rows, cols = linear_sum_assignment(-iou)
        for r, k in zip(rows, cols, strict=True):
            if iou[r, k] < self.min_iou:
                continue
            c.matched += 1
            oid, tid = oids[r], tracks[k].track_id
            last = self._last.get(oid)
            if last is not None and last[0] != tid:
                if frame_index - last[1] <= self.gap_frames + 1:
                    c.continuous += 1
                    c.events.append((frame_index, oid, last[0], tid))
                else:
                    c.reentry += 1
            self._last[oid] = (tid, frame_index)


def fly(
    room: Room,
    cfg: CompanionConfig,
    poses: Sequence[tuple[float, float, float]],
    trackers: dict[str, TrackFn],
    intrinsics: CameraIntrinsics | None = None,
    seed: int = 0,
    altitude_m: float = 1.0,
    gap_frames: int = 15,
) -> dict[str, tuple[SwitchCount, list[float]]]:
    """Render and detect (oracle) along ``poses``, feeding the same detections to every
    tracker. Returns, per tracker, its switch count and per-frame update times (seconds)."""
    intr = intrinsics or cfg.camera.intrinsics()
    renderer = RoomRenderer(room, [c.name for c in cfg.classes], intr, seed=seed)
    oracle = OracleDetector.from_config(cfg.detector, [c.name for c in cfg.classes], seed=seed)
    T_body_camera = cfg.camera.extrinsics.T_body_camera()
    counters = {name: SwitchCounter(gap_frames) for name in trackers}
    times: dict[str, list[float]] = {name: [] for name in trackers}
    for i, (x, y, yaw) in enumerate(poses):
        T = pose_from_xyz_rpy(x, y, altitude_m, yaw_rad=yaw) @ T_body_camera
        frame = renderer.render(T, stamp_s=i / cfg.camera.rate_hz, index=i)
        dets = oracle.detect_frame(frame)
        gt = {oid: box for oid, (box, _n) in oracle.ground_truth_boxes(frame).items()}
        for name, track in trackers.items():
            t0 = time.perf_counter()
            tracks = track(dets, frame.rgb)
            times[name].append(time.perf_counter() - t0)
            counters[name].add(i, gt, tracks)
    return {name: (counters[name].count, times[name]) for name in trackers}
