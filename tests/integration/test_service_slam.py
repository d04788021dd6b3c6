"""The service with SLAM localization flying the demo mission while the autopilot's odometry
drifts: the SLAM pose stays on the truth, PX4 (the mock) fuses it as external vision, and the
status reports it."""

from __future__ import annotations

import asyncio
import bisect
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from companion.config import load_config
from companion.service.app import CompanionService
from companion.sim.demo_e2e import run_e2e
from companion.sim.sim_world import SimWorld
from semmap.errors import ConfigError

#: A closed-loop flight: the full suite runs it, `make check` does not.
pytestmark = pytest.mark.slow

pytest.importorskip("open3d")

SMALL: dict[str, Any] = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    # Heading drift 4x the figure so a one-minute flight shows it.
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4, "odometry_drift": True,
            "odometry_scale_error": 0.03, "odometry_heading_drift_deg_s": 2.0},
    "service": {"localization": "slam"},
    "link": {"external_vision": True},
}


def _cfg(tmp_path: Path, data: dict[str, Any]) -> Any:
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)


def test_slam_mode_needs_external_vision(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, {**SMALL, "link": {"external_vision": False}})
    with pytest.raises(ConfigError, match="external_vision"):
        CompanionService(cfg, SimWorld(cfg).frame_source())


def test_slam_keeps_the_pose_while_the_odometry_drifts(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, SMALL)
    samples: list[tuple[float, float, float]] = []  # (t, SLAM error m, odometry error m)
    statuses: list[str] = []
    health: list[bool] = []

    async def inject(world: Any, svc: CompanionService, broker: Any) -> None:
        ap = world.autopilot
        stamps: list[float] = []
        truth: list[np.ndarray] = []
        while True:
            stamp, T = ap.T_map_body()
            stamps.append(float(stamp))
            truth.append(np.asarray(T)[:2, 3].copy())
            st = svc.localization.latest()
            # The camera stamps on time.monotonic; the truth is on the mock's clock.
            st_stamp = ap.stamp_of_monotonic(st.stamp_s) if st is not None else 0.0
            # In flight only: once landed the camera sees the floor, the SLAM falls back to the
            # (still) odometry and its error freezes at the touchdown value; counted every 50 ms
            # until disarm, that one value was 5-8 % of the samples and, on a slow run, set the
            # p95 (one fresh-clone run failed at p95 0.287 m: its touchdown error, 0.280 m,
            # repeated over the last samples).
            airborne = float(np.asarray(T)[2, 3]) > 0.3
            if st is not None and ap.armed and airborne and stamps[0] < st_stamp:
                k = min(bisect.bisect_left(stamps, st_stamp), len(stamps) - 1)
                n, e, _ = ap.estimator.raw_pose_ned
                odo_err = math.dist((e, n), truth[-1])
                samples.append((st.stamp_s, float(np.linalg.norm(st.T_map_body[:2, 3] - truth[k])), odo_err))
                statuses.append(st.status)
                health.append(svc.localization.health()["localization"])
            await asyncio.sleep(0.05)

    result = asyncio.run(run_e2e(cfg, tmp_path / "out", use_broker=False, timeout_s=100.0, inject=inject))
    s = result.summary
    assert s["collisions"] == 0, s["collision_points_room_xy_m"]
    assert s["waypoints_reached"] >= 2, s["legs"]
    assert len(samples) > 100
    errs = np.array([e for _, e, _ in samples])
    odo = np.array([o for _, _, o in samples])
    # The drifting odometry wanders off (about 2 m); the live SLAM pose stays within a bound
    # (this 160 px camera at the demo's speed; bench/slam.py measures the accuracy). With the
    # SLAM's motion prior dead-reckoned from the telemetry's velocity and yaw rate (shipped SLAM
    # settings), 8 runs on a 2-core machine busy with a training job: p95 0.065-0.098 m, max
    # 0.085-0.108 m. With the prior taken from the increments of PX4's position estimate,
    # which fuses the SLAM's own vision and so hands its corrections back as motion (and the
    # weaker translation prior, 1.0, this test then set), 11 runs: p95 0.13-0.27 m, max
    # 0.16-0.30 m, 3 of them over the old 0.25 m bound: the pose and the estimate chased each
    # other off the truth while the drone turned on the spot with few hits in view. The bounds
    # leave room for a loaded CI machine and fail both that feedback and a pose that follows
    # the odometry.
    loc = result.report.localization
    detail = (f"SLAM error p95 {np.percentile(errs, 95):.3f} max {errs.max():.3f} m, odometry max "
              f"{odo.max():.3f} m, {loc}")
    assert odo.max() > 0.5, detail
    assert float(np.percentile(errs, 95)) < 0.15, detail
    assert float(errs.max()) < 0.20, detail
    assert float(errs.max()) < 0.5 * float(odo.max()), detail
    assert loc["scans"] > 50 and loc["vision_sent"] > 300, detail
    # Judged in flight only: on the floor before take-off and after landing the camera sees
    # little but floor, and how long the service sits there depends on the machine's load.
    assert statuses.count("degenerate_fallback_odometry") < 0.25 * len(statuses), detail
    assert statuses.count("ok") + statuses.count("partial_odometry") > 0.75 * len(statuses), detail
    assert sum(health) > 0.75 * len(health), detail
