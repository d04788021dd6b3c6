"""One per-frame step: the service, ``companion map`` and the benches map a frame the same way."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import load_config
from companion.service.perception_worker import PerceptionPipeline, new_semantic_map
from semmap.errors import MapError
from semmap.pipeline import MappingPipeline, OneTrackPerBox, step_aware_tracker
from semmap.types import Detection, Frame
from tests.unit.test_geometry import FLOOR, K, box_of, camera_pose, render
from tests.unit.test_touching_furniture import FAR_CHAIR, TABLE


class _Boxes:
    """A detector that reports the image boxes of given objects at a frame's pose."""

    def __init__(self, objects: list[tuple[list, str]]) -> None:
        self.objects = objects
        self.calls = 0

    def detect_frame(self, frame: Frame) -> list[Detection]:
        self.calls += 1
        assert frame.T_map_camera is not None
        return [Detection(box_of(parts, frame.T_map_camera), 0.8, cls) for parts, cls in self.objects]


def _frame(T: np.ndarray, index: int) -> Frame:
    depth = render(TABLE + FAR_CHAIR + [FLOOR], T)
    rgb = np.zeros((K.height_px, K.width_px, 3), np.uint8)
    return Frame(0.5 * index, rgb, depth, K, T_map_camera=T, index=index)


def _config():  # type: ignore[no-untyped-def]
    cfg = load_config(None)
    return cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"depth_min_m": 0.3, "depth_max_m": 8.0})})


def test_the_service_measures_a_chair_behind_a_table_with_the_frames_other_boxes() -> None:
    cfg = _config()
    smap = new_semantic_map(cfg)
    detector = _Boxes([(TABLE, "desk"), (FAR_CHAIR, "chair")])
    pipeline = PerceptionPipeline(cfg, smap, detector)  # type: ignore[arg-type]
    stages = pipeline.process(_frame(camera_pose(0.6, 0.9, 1.4, 0.0, 30.0), 0))
    assert set(stages) == {"detect", "track", "geometry", "grid"} and pipeline.frames_done == 1
    assert smap.object_map is not None
    objs = {o.class_name: o for o in smap.object_map.objects(confirmed_only=False)}
    # Box by box, the chair's box holds only the nearer table top and shows no chair at all.
    assert set(objs) == {"desk", "chair"}
    chair = objs["chair"]
    assert chair.z_max_m > 0.95 and abs(chair.footprint_center_xy_m[0] - 3.1) < 0.25
    assert objs["desk"].z_max_m < 0.8


def test_keyframes_far_apart_map_one_table_and_chair_not_two() -> None:
    cfg = _config()
    smap = new_semantic_map(cfg)
    pipeline = PerceptionPipeline(cfg, smap, _Boxes([(TABLE, "desk"), (FAR_CHAIR, "chair")]))  # type: ignore[arg-type]
    poses = [camera_pose(0.6, 0.9, 1.4, 0.0, 30.0), camera_pose(0.7, 0.3, 1.4, 0.35, 30.0),
             camera_pose(0.7, 1.5, 1.4, -0.35, 30.0)]
    for i, T in enumerate(poses):
        pipeline.process(_frame(T, i))
    assert smap.object_map is not None
    names = sorted(o.class_name for o in smap.object_map.objects(confirmed_only=False))
    assert names == ["chair", "desk"]
    assert pipeline.step.tracker.steps == 3  # type: ignore[attr-defined]  # every frame a keyframe


def test_given_detections_and_a_detector_map_a_frame_alike() -> None:
    cfg = _config()
    T = camera_pose(0.6, 0.9, 1.4, 0.0, 30.0)
    frame = _frame(T, 0)
    detector = _Boxes([(TABLE, "desk"), (FAR_CHAIR, "chair")])
    by_detector = MappingPipeline(new_semantic_map(cfg), cfg.classes, cfg.geometry, OneTrackPerBox(), detector,
                                  depth_range_m=(0.3, 8.0)).register_frame(frame)
    given = MappingPipeline(new_semantic_map(cfg), cfg.classes, cfg.geometry, step_aware_tracker(cfg.tracker),
                            depth_range_m=(0.3, 8.0)).register_frame(frame, detections=detector.detect_frame(frame))
    assert [o.class_name for o in by_detector.observations] == [o.class_name for o in given.observations]
    for a, b in zip(by_detector.observations, given.observations, strict=True):
        np.testing.assert_allclose(a.footprint_xy_m, b.footprint_xy_m)
    np.testing.assert_array_equal(by_detector.integration.scan.is_hit, given.integration.scan.is_hit)


def test_the_step_refuses_what_it_cannot_map() -> None:
    cfg = _config()
    T = camera_pose(0.6, 0.9, 1.4, 0.0, 30.0)
    step = MappingPipeline(new_semantic_map(cfg), cfg.classes, cfg.geometry, OneTrackPerBox(),
                           depth_range_m=(0.3, 8.0))
    frame = _frame(T, 4)
    with pytest.raises(MapError, match="frame 4: no detections given"):
        step.register_frame(frame)
    with pytest.raises(MapError, match=r"unknown classes \['bench'\]"):
        step.register_frame(frame, detections=[Detection((1.0, 1.0, 50.0, 50.0), 0.9, "bench")])
    unposed = Frame(0.0, frame.rgb, frame.depth_m, K, index=5)
    with pytest.raises(MapError, match="frame 5: no camera pose"):
        step.register_frame(unposed, detections=[])


def test_a_view_without_floor_measures_no_object_and_costs_none_a_miss() -> None:
    cfg = _config()
    smap = new_semantic_map(cfg)
    detector = _Boxes([(TABLE, "desk"), (FAR_CHAIR, "chair")])
    step = MappingPipeline(smap, cfg.classes, cfg.geometry, OneTrackPerBox(), detector, depth_range_m=(0.3, 8.0))
    T = camera_pose(0.6, 0.9, 1.4, 0.0, 30.0)
    seen = step.register_frame(_frame(T, 0))
    assert seen.floor_height_m is not None and abs(seen.floor_height_m) < 0.01 and len(seen.observations) == 2
    assert smap.object_map is not None
    before = {o.object_id: o.existence for o in smap.object_map.objects(confirmed_only=False)}
    # The same boxes on a frame whose floor is raised out of reach (a bad pose height).
    lifted = _frame(T, 1)
    T_up = T.copy()
    T_up[2, 3] += 0.5
    blind = step.register_frame(Frame(lifted.stamp_s, lifted.rgb, lifted.depth_m, K, T_map_camera=T_up, index=1))
    assert blind.floor_height_m is None and blind.observations == [] and step.views_without_floor == 1
    after = {o.object_id: o.existence for o in smap.object_map.objects(confirmed_only=False)}
    assert after == before
