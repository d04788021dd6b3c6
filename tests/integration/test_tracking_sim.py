"""Tracking on a simulated flight: renderer -> oracle detector -> BoT-SORT with CMC.

The drone hovers in a generated furnished room and yaws back and forth at 60 deg/s (4 deg per
frame at 15 Hz), then flies a short leg. Every object must keep its track id while it stays in
view: at most one identity switch per 100 frames.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

pytest.importorskip("open3d")

from companion.config import CompanionConfig  # noqa: E402
from companion.sim.groundtruth import clearance_m, path_collides  # noqa: E402
from companion.sim.render import RoomRenderer  # noqa: E402
from companion.sim.world import generate_room  # noqa: E402
from semmap.detection.oracle import OracleDetector  # noqa: E402
from semmap.frames import pose_from_xyz_rpy  # noqa: E402
from semmap.tracking.botsort import BoTSORT  # noqa: E402
from semmap.tracking.matching import iou_matrix  # noqa: E402
from semmap.types import CameraIntrinsics  # noqa: E402

RATE_HZ = 15.0
YAW_STEP = math.radians(60.0) / RATE_HZ
ALT_M = 1.0
#: Quarter-VGA keeps the test fast; focal length scaled with it (D455 at 320x240).
INTR = CameraIntrinsics(191.5, 191.5, 160.0, 120.0, 320, 240)


def flight(room) -> list[tuple[float, float, float]]:
    """Yaw +120, hold, -240, hold, +120 deg at 60 deg/s, then a 1 m leg: (x, y, yaw) poses."""
    xs, ys = np.meshgrid(np.arange(0.5, room.width_m - 0.5, 0.25), np.arange(0.5, room.depth_m - 0.5, 0.25))
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, ALT_M)])
    clear = clearance_m(room, pts, 0.3)
    centre = np.array([room.width_m / 2, room.depth_m / 2])
    ok = clear > 0.6
    start = pts[ok][np.argmin(np.linalg.norm(pts[ok, :2] - centre, axis=1))]
    x, y, yaw = float(start[0]), float(start[1]), 0.0
    poses = []
    for turn_deg, hold in ((120, 15), (-240, 15), (120, 0)):
        for _ in range(int(round(abs(turn_deg) / 4.0))):
            yaw += math.copysign(YAW_STEP, turn_deg)
            poses.append((x, y, yaw))
        poses += [(x, y, yaw)] * hold
    for heading in np.linspace(0, 2 * math.pi, 16, endpoint=False):
        end = (x + math.cos(heading), y + math.sin(heading))
        seg = np.array([[x, y, ALT_M], [end[0], end[1], ALT_M]])
        if not path_collides(room, seg, 0.35, 0.3):
            break
    while abs(math.remainder(heading - yaw, 2 * math.pi)) > YAW_STEP:
        yaw += math.copysign(YAW_STEP, math.remainder(heading - yaw, 2 * math.pi))
        poses.append((x, y, yaw))
    for k in range(1, 31):  # 1 m at 0.5 m/s
        poses.append((x + k / 30 * (end[0] - x), y + k / 30 * (end[1] - y), yaw))
    return poses


@pytest.mark.slow
def test_objects_keep_their_ids_through_60_deg_per_s_turns() -> None:
    cfg = CompanionConfig()
    names = [c.name for c in cfg.classes]
    room = generate_room(3, width_m=7.0, depth_m=5.0, n_objects=7, class_names=names)
    renderer = RoomRenderer(room, names, INTR, seed=3)
    oracle = OracleDetector.from_config(cfg.detector, names, seed=3)
    tracker = BoTSORT.from_config(cfg.tracker)
    gap = tracker.max_time_lost
    T_body_camera = cfg.camera.extrinsics.T_body_camera()

    poses = flight(room)
    last: dict[int, tuple[int, int]] = {}  # object id -> (track id, frame)
    switches, matched, visible, turn_shift_px = 0, 0, 0, []
    for i, (x, y, yaw) in enumerate(poses):
        frame = renderer.render(pose_from_xyz_rpy(x, y, ALT_M, yaw_rad=yaw) @ T_body_camera, index=i)
        tracks = tracker.update(oracle.detect_frame(frame), frame.rgb)
        if 0 < i < 30:  # the first turn: pure yaw, the image centre shifts sideways
            c = tracker.last_warp @ [INTR.cx_px, INTR.cy_px, 1.0]
            turn_shift_px.append(c[0] / c[2] - INTR.cx_px)
        gt = {oid: box for oid, (box, _) in oracle.ground_truth_boxes(frame).items()}
        visible += len(gt)
        if not gt or not tracks:
            continue
        oids = list(gt)
        iou = iou_matrix(np.array([gt[o] for o in oids]), np.array([t.xyxy_px for t in tracks]))
        for r, c in zip(*linear_sum_assignment(-iou), strict=True):
            if iou[r, c] < 0.5:
                continue
            matched += 1
            oid, tid = oids[r], tracks[c].track_id
            if oid in last and last[oid][0] != tid and i - last[oid][1] <= gap + 1:
                switches += 1
            last[oid] = (tid, i)

    n = len(poses)
    assert n >= 150
    # CMC sees the yaw: 4 deg per frame is fx * tan(4 deg) = 13.4 px of sideways image motion.
    assert abs(float(np.median(turn_shift_px))) == pytest.approx(INTR.fx_px * math.tan(YAW_STEP), rel=0.25)
    assert visible > 100, "the flight should see furniture"
    assert matched / visible > 0.6, f"tracks cover only {matched}/{visible} visible objects"
    assert switches <= n / 100, f"{switches} identity switches in {n} frames"
