"""Keyframes and video alike: camera steps too large for the image tracker go to 3D association."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from semmap.frames import pose_from_xyz_rpy
from semmap.tracking.botsort import BoTSORT
from semmap.tracking.camera_steps import StepAwareTracker, camera_step
from semmap.types import Detection, Track


class _Recorder:
    """An image tracker that keeps one id per box position and counts resets."""

    def __init__(self) -> None:
        self.resets = 0
        self.calls = 0

    def update(self, detections: Sequence[Detection], image_rgb: object = None) -> list[Track]:
        self.calls += 1
        return [Track(100 + i, d.xyxy_px, d.score, d.class_name) for i, d in enumerate(detections)]

    def reset(self) -> None:
        self.resets += 1


BOXES = [Detection((10.0, 10.0, 60.0, 90.0), 0.9, "chair"), Detection((200.0, 50.0, 400.0, 200.0), 0.4, "desk")]


def test_camera_step_measures_translation_and_rotation() -> None:
    a = pose_from_xyz_rpy(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    b = pose_from_xyz_rpy(0.3, 0.4, 1.0, 0.0, 0.0, np.radians(20.0))
    d, deg = camera_step(a, b)
    assert d == pytest.approx(0.5) and deg == pytest.approx(20.0)


def test_video_steps_keep_the_image_tracks_and_keyframe_steps_give_fresh_ids() -> None:
    inner = _Recorder()
    tr = StepAwareTracker(inner, max_step_m=0.15, max_step_deg=10.0)
    poses = [pose_from_xyz_rpy(0.05 * i, 0.0, 1.0, 0.0, 0.0, 0.0) for i in range(3)]
    ids = [[t.track_id for t in tr.update(BOXES, None, T)] for T in poses]
    assert tr.steps == 1 and ids[0] != ids[1]  # the first frame has no history: a step
    assert ids[1] == ids[2] and tr.steps == 1  # video: the image tracker's ids
    jump = pose_from_xyz_rpy(0.6, 0.0, 1.0, 0.0, 0.0, np.radians(15.0))
    after = [t.track_id for t in tr.update(BOXES, None, jump)]
    assert tr.steps == 2 and inner.resets == 2
    assert len(after) == 2 and not set(after) & set(ids[1])  # no id continues across the step
    # Every box of a keyframe is a track, the low-scoring one too (the object map weighs it).
    assert [t.class_name for t in tr.update(BOXES, None, pose_from_xyz_rpy(0.6, 0.7, 1.0, 0, 0, 0))] == ["chair", "desk"]


def test_botsort_ids_never_jump_across_a_keyframe_step() -> None:
    tr = StepAwareTracker(BoTSORT(frame_rate_hz=15.0))
    first = tr.update([Detection((100.0, 100.0, 200.0, 300.0), 0.9, "chair")], None, np.eye(4))
    # 0.6 m later the same pixels show another chair: BoT-SORT alone would continue the track.
    step = pose_from_xyz_rpy(0.6, 0.0, 0.0, 0.0, 0.0, 0.0)
    second = tr.update([Detection((105.0, 100.0, 205.0, 300.0), 0.9, "chair")], None, step)
    assert first and second and first[0].track_id != second[0].track_id
