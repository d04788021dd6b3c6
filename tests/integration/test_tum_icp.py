"""Relative motion from real depth: TUM fr1/xyz frame pairs against the ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench._icp import register_depth_frames
from companion.sources import load_tum_pair
from companion.sources.recorded import TUM_INTRINSICS
from semmap.frames import invert


@pytest.mark.parametrize("case", ["case_1", "case_2"])
def test_icp_on_tum_fr1_xyz_is_within_2cm_and_1deg(real_data: Path, case: str) -> None:
    # The folder's intrinsics.json is a ROS default; the official fr1 calibration is used.
    prev, curr = load_tum_pair(real_data / "rgbd" / "tum_fr1_xyz" / case, intrinsics=TUM_INTRINSICS["freiburg1"])
    T_prev_curr_true = invert(prev.T_map_camera) @ curr.T_map_camera
    res = register_depth_frames(curr.depth_m, prev.depth_m, prev.intrinsics)
    err = invert(T_prev_curr_true) @ res.T_target_source
    err_t_m = float(np.linalg.norm(err[:3, 3]))
    err_deg = float(np.degrees(Rotation.from_matrix(err[:3, :3]).magnitude()))
    assert err_t_m <= 0.02, f"{case}: translation error {err_t_m:.4f} m"
    assert err_deg <= 1.0, f"{case}: rotation error {err_deg:.3f} deg"
    # The motion is real (not the identity passing by chance).
    assert np.linalg.norm(T_prev_curr_true[:3, 3]) > 0.015
