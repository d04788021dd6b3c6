"""Letterbox geometry and pixel conventions, and class-aware NMS against a brute-force one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semmap.detection.letterbox import PAD_VALUE, letterbox
from semmap.detection.nms import nms_class_aware
from semmap.errors import FrameError
from semmap.tracking.matching import iou_matrix


@settings(max_examples=40, deadline=None)
@given(st.integers(16, 900), st.integers(16, 900), st.sampled_from([(320, 320), (640, 640), (256, 416)]),
       st.sampled_from(["yolov8", "yolox"]))
def test_boxes_map_back_to_where_they_were(h, w, hw_in, style) -> None:
    img = np.zeros((h, w, 3), np.uint8)
    _, tf = letterbox(img, hw_in, style)
    box = np.array([[0.1 * w, 0.2 * h, 0.7 * w, 0.9 * h]], np.float32)
    fwd = box.copy()
    fwd[:, [0, 2]] = box[:, [0, 2]] * tf.scale + tf.pad_left_px
    fwd[:, [1, 3]] = box[:, [1, 3]] * tf.scale + tf.pad_top_px
    assert np.all(fwd[:, [0, 2]] <= hw_in[1] + 1e-3) and np.all(fwd[:, [1, 3]] <= hw_in[0] + 1e-3)
    np.testing.assert_allclose(tf.boxes_to_original(fwd), box, rtol=1e-4, atol=1e-3)


def test_yolov8_convention_rgb_unit_range_centred_padding() -> None:
    img = np.zeros((480, 640, 3), np.uint8)
    img[..., 0] = 200  # red
    t, tf = letterbox(img, (320, 320), "yolov8")
    assert t.shape == (1, 3, 320, 320) and t.dtype == np.float32
    assert (tf.pad_left_px, tf.pad_top_px, tf.scale) == (0.0, 40.0, 0.5)
    np.testing.assert_allclose(t[0, :, 0, 0], PAD_VALUE / 255.0, rtol=1e-6)  # top padding
    np.testing.assert_allclose(t[0, :, 319, 0], PAD_VALUE / 255.0, rtol=1e-6)  # bottom padding
    np.testing.assert_allclose(t[0, :, 160, 160], [200 / 255.0, 0.0, 0.0], rtol=1e-6)


def test_yolox_convention_bgr_raw_range_bottom_right_padding() -> None:
    img = np.zeros((480, 640, 3), np.uint8)
    img[..., 0] = 200
    t, tf = letterbox(img, (320, 320), "yolox")
    assert (tf.pad_left_px, tf.pad_top_px, tf.scale) == (0.0, 0.0, 0.5)
    np.testing.assert_allclose(t[0, :, 0, 0], [0.0, 0.0, 200.0])  # BGR: red is last
    np.testing.assert_allclose(t[0, :, 300, 10], PAD_VALUE)  # below the 240 image rows


def test_bad_image_is_a_frame_error() -> None:
    with pytest.raises(FrameError, match="uint8"):
        letterbox(np.zeros((10, 10, 3), np.float32), (320, 320), "yolov8")
    with pytest.raises(FrameError, match="shape"):
        letterbox(np.zeros((10, 10), np.uint8), (320, 320), "yolov8")


def _greedy_nms(boxes, scores, labels, thr):
    keep = []
    for i in np.argsort(-scores, kind="stable"):
        if all(labels[j] != labels[i] or iou_matrix(boxes[i:i + 1], boxes[j:j + 1])[0, 0] <= thr for j in keep):
            keep.append(i)
    return keep


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 200), st.floats(0, 200), st.floats(5, 80), st.floats(5, 80),
                          st.floats(0.01, 1.0), st.integers(0, 2)), min_size=1, max_size=25),
       st.sampled_from([0.3, 0.5, 0.7]))
def test_nms_matches_greedy_class_aware_suppression(rows, thr) -> None:
    a = np.array(rows, dtype=np.float64)
    boxes = np.column_stack([a[:, 0], a[:, 1], a[:, 0] + a[:, 2], a[:, 1] + a[:, 3]]).astype(np.float32)
    # Distinct scores: ties make "best first" ambiguous.
    scores = (a[:, 4] + np.arange(len(a)) * 1e-4).astype(np.float32)
    labels = a[:, 5].astype(np.int64)
    got = nms_class_aware(boxes, scores, labels, thr, max_detections=1000)
    want = _greedy_nms(boxes.astype(np.float64), scores, labels, thr)
    assert sorted(got.tolist()) == sorted(want)
    assert list(scores[got]) == sorted(scores[got], reverse=True)
