"""BoT-SORT, its Kalman filter and matching, and the SORT baseline on scripted detections."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench._sort_baseline import SORT
from semmap.config import TrackerConfig
from semmap.errors import FrameError
from semmap.tracking import kalman
from semmap.tracking.botsort import BoTSORT
from semmap.tracking.matching import iou_matrix, linear_assignment
from semmap.types import Detection


def det(u: float, v: float, w: float = 60.0, h: float = 80.0, score: float = 0.9,
        cls: str = "chair") -> Detection:
    """A detection centred at (u, v)."""
    return Detection((u - w / 2, v - h / 2, u + w / 2, v + h / 2), score, cls)


def tracker(**kw) -> BoTSORT:
    kw.setdefault("frame_rate_hz", 30.0)
    return BoTSORT(**kw)


def centre(t) -> tuple[float, float]:
    u0, v0, u1, v1 = t.xyxy_px
    return (u0 + u1) / 2, (v0 + v1) / 2


# --- Kalman filter -----------------------------------------------------------------------

def test_kalman_noise_model_is_botsorts() -> None:
    m, P = kalman.initiate(np.array([[100.0, 50.0, 40.0, 80.0]]))
    std = np.sqrt(np.diag(P[0]))
    # 2 * (1/20) * w|h for positions, 10 * (1/160) * w|h for velocities.
    np.testing.assert_allclose(std, [4.0, 8.0, 4.0, 8.0, 2.5, 5.0, 2.5, 5.0])
    m2, P2 = kalman.predict(m, P)
    q = np.array([2.0, 4.0, 2.0, 4.0, 0.25, 0.5, 0.25, 0.5]) ** 2
    F = kalman.F
    np.testing.assert_allclose(P2[0], F @ P[0] @ F.T + np.diag(q))


def test_kalman_learns_a_constant_velocity() -> None:
    m, P = kalman.initiate(np.array([[0.0, 0.0, 50.0, 50.0]]))
    for k in range(1, 30):
        m, P = kalman.predict(m, P)
        m, P = kalman.update(m, P, np.array([[5.0 * k, -2.0 * k, 50.0, 50.0]]))
    assert m[0, 4] == pytest.approx(5.0, abs=0.05)
    assert m[0, 5] == pytest.approx(-2.0, abs=0.05)
    m, _ = kalman.predict(m, P)
    assert m[0, 0] == pytest.approx(150.0, abs=0.5)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 600), st.floats(0, 400), st.floats(5, 200), st.floats(5, 200)),
                min_size=1, max_size=6),
       st.floats(-20, 20), st.floats(-20, 20))
def test_kalman_batched_update_equals_one_by_one(boxes, du, dv) -> None:
    z = np.array(boxes)
    m, P = kalman.predict(*kalman.initiate(z))
    meas = z + np.array([du, dv, 1.0, -1.0])
    mb, Pb = kalman.update(m, P, meas)
    for i in range(len(z)):
        mi, Pi = kalman.update(m[i:i + 1], P[i:i + 1], meas[i:i + 1])
        np.testing.assert_allclose(mb[i], mi[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(Pb[i], Pi[0], rtol=1e-9, atol=1e-9)
    # The covariance stays symmetric positive definite.
    assert np.all(np.linalg.eigvalsh((Pb + Pb.transpose(0, 2, 1)) / 2) > 0)


def test_affine_moves_centre_and_rotates_pairs() -> None:
    m, P = kalman.initiate(np.array([[100.0, 50.0, 40.0, 80.0]]))
    m[0, 4:6] = (3.0, 1.0)
    warp = np.array([[1.0, 0.0, 12.0], [0.0, 1.0, -5.0]])
    m2, P2 = kalman.apply_warp(m, P, warp)
    np.testing.assert_allclose(m2[0], [112.0, 45.0, 40.0, 80.0, 3.0, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(P2, P)
    c, s = np.cos(0.1), np.sin(0.1)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0]])
    m3, _ = kalman.apply_warp(m, P, rot)
    np.testing.assert_allclose(m3[0, :2], rot[:, :2] @ [100.0, 50.0])
    np.testing.assert_allclose(m3[0, 4:6], rot[:, :2] @ [3.0, 1.0])


def test_homography_warp_uses_the_local_jacobian() -> None:
    # A yaw-like homography: the centre moves exactly, sizes scale by the local derivative.
    K = np.array([[383.0, 0.0, 320.0], [0.0, 383.0, 240.0], [0.0, 0.0, 1.0]])
    a = np.deg2rad(4.0)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    H = K @ R @ np.linalg.inv(K)
    m, P = kalman.initiate(np.array([[550.0, 300.0, 40.0, 80.0], [100.0, 100.0, 30.0, 30.0]]))
    m2, P2 = kalman.apply_warp(m, P, H)

    def f(x, y):
        p = H @ [x, y, 1.0]
        return p[:2] / p[2]

    for i in range(2):
        x, y = m[i, :2]
        np.testing.assert_allclose(m2[i, :2], f(x, y), rtol=1e-12)
        eps = 1e-4
        J = np.column_stack([(f(x + eps, y) - f(x - eps, y)) / (2 * eps),
                             (f(x, y + eps) - f(x, y - eps)) / (2 * eps)])
        np.testing.assert_allclose(m2[i, 2:4], J @ m[i, 2:4], rtol=1e-6)
        np.testing.assert_allclose(P2[i, :2, :2], J @ P[i, :2, :2] @ J.T, rtol=1e-6)
    # An affine given as (3, 3) behaves exactly like the (2, 3) form (BoT-SORT's multi_gmc).
    A = np.array([[0.99, -0.02, 5.0], [0.02, 0.99, -3.0]])
    np.testing.assert_allclose(kalman.apply_warp(m, P, A)[0], kalman.apply_warp(m, P, np.vstack([A, [0, 0, 1]]))[0])


# --- matching ----------------------------------------------------------------------------

@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 100), st.floats(0, 100), st.floats(1, 50), st.floats(1, 50)),
                min_size=1, max_size=5))
def test_iou_matrix_properties(boxes) -> None:
    b = np.array([(u, v, u + w, v + h) for u, v, w, h in boxes])
    m = iou_matrix(b, b)
    np.testing.assert_allclose(np.diag(m), 1.0)
    np.testing.assert_allclose(m, m.T, atol=1e-12)
    assert np.all((m >= 0) & (m <= 1 + 1e-12))


def test_iou_value() -> None:
    assert iou_matrix(np.array([[0, 0, 10, 10]]), np.array([[5, 0, 15, 10]]))[0, 0] == pytest.approx(1 / 3)


def test_linear_assignment_respects_the_threshold() -> None:
    cost = np.array([[0.1, 0.9], [0.95, 0.85]])
    matches, ur, uc = linear_assignment(cost, 0.8)
    assert matches.tolist() == [[0, 0]]
    assert ur.tolist() == [1] and uc.tolist() == [1]
    # An over-threshold pair must not displace a valid one.
    cost = np.array([[0.5, 0.3], [0.9, 2.0]])
    matches, _, _ = linear_assignment(cost, 0.8)
    assert matches.tolist() == [[0, 1]]


# --- BoT-SORT ----------------------------------------------------------------------------

def test_one_moving_object_keeps_one_id() -> None:
    trk = tracker()
    ids = set()
    for k in range(40):
        out = trk.update([det(100 + 6 * k, 200 + 2 * k)])
        assert len(out) == 1
        ids.add(out[0].track_id)
    assert ids == {1}
    u, v = centre(out[0])
    assert u == pytest.approx(100 + 6 * 39, abs=2.0) and v == pytest.approx(200 + 2 * 39, abs=2.0)
    assert out[0].age_frames == 39


def test_crossing_objects_of_different_classes_keep_their_ids() -> None:
    trk = tracker()
    seen: dict[str, set[int]] = {"chair": set(), "desk": set()}
    for k in range(30):
        dets = [det(100 + 10 * k, 200, cls="chair"), det(390 - 10 * k, 205, cls="desk")]
        for t in trk.update(dets):
            seen[t.class_name].add(t.track_id)
    assert len(seen["chair"]) == 1 and len(seen["desk"]) == 1
    assert seen["chair"] != seen["desk"]


def test_new_track_needs_a_confident_detection_and_a_second_frame() -> None:
    trk = tracker()
    trk.update([det(100, 100)])  # frame 1: confirmed at once (reference behaviour)
    assert [t.track_id for t in trk.update([det(100, 100), det(400, 300, score=0.55)])] == [1]
    # 0.55 >= track_high (0.5) but < new_track (0.6): never starts a track.
    out = trk.update([det(100, 100), det(400, 300, score=0.55)])
    assert [t.track_id for t in out] == [1]
    # A confident newcomer is unconfirmed for one frame, reported from its second.
    assert [t.track_id for t in trk.update([det(100, 100), det(400, 300, score=0.9)])] == [1]
    out = trk.update([det(100, 100), det(402, 300, score=0.9)])
    assert sorted(t.track_id for t in out) == [1, 2]


def test_unconfirmed_track_is_removed_when_not_seen_again() -> None:
    trk = tracker()
    trk.update([det(100, 100)])
    trk.update([det(100, 100), det(400, 300)])  # one-frame false positive
    trk.update([det(100, 100)])
    out = trk.update([det(100, 100), det(400, 300)])  # comes back: a new, unconfirmed track
    assert [t.track_id for t in out] == [1]


def test_low_score_detections_keep_a_track_alive() -> None:
    # Second stage: a partly occluded object scores 0.3 for a while.
    for second_stage, expect_same_id in ((True, True), (False, False)):
        low = 0.1 if second_stage else 0.45  # low >= 0.45 excludes 0.3 from stage two
        trk = tracker(track_low_thresh=low, track_buffer_frames=2)
        for k in range(5):
            trk.update([det(100 + 4 * k, 200)])
        outs = [trk.update([det(100 + 4 * k, 200, score=0.3)]) for k in range(5, 15)]
        final = trk.update([det(100 + 4 * 15, 200, score=0.9)])
        final = trk.update([det(100 + 4 * 16, 200, score=0.9)])
        if expect_same_id:
            assert all(len(o) == 1 and o[0].track_id == 1 for o in outs)
            assert final[0].track_id == 1
        else:
            assert all(len(o) == 0 for o in outs)
            assert final[0].track_id != 1


def test_lost_track_is_recovered_within_the_buffer_and_forgotten_after() -> None:
    trk = tracker(track_buffer_frames=10)
    for k in range(10):
        trk.update([det(100 + 3 * k, 200)])
    for _ in range(5):
        assert trk.update([]) == []
    assert trk.lost_count == 1
    out = trk.update([det(100 + 3 * 15, 200)])
    assert [t.track_id for t in out] == [1]  # re-activated with its old id
    for _ in range(12):
        trk.update([])
    assert trk.lost_count == 0
    trk.update([det(100 + 3 * 15, 200)])
    out = trk.update([det(100 + 3 * 15, 200)])
    assert [t.track_id for t in out] == [2]


def test_camera_motion_compensation_keeps_ids_through_a_fast_turn() -> None:
    # The camera yaws: every box jumps 90 px left between frames 10 and 11 (no IoU overlap).
    def scene(shift: float) -> list[Detection]:
        return [det(200 - shift, 200), det(330 - shift, 220, cls="desk"), det(450 - shift, 180)]

    def run(with_warp: bool) -> set[int]:
        trk = tracker()
        ids: set[int] = set()
        for k in range(20):
            shift = 0.0 if k < 10 else 90.0
            warp = None
            if with_warp:
                warp = np.array([[1.0, 0.0, -90.0 if k == 10 else 0.0], [0.0, 1.0, 0.0]])
            ids |= {t.track_id for t in trk.update(scene(shift), warp=warp)}
        return ids

    assert run(True) == {1, 2, 3}
    assert len(run(False)) == 6


def test_cmc_on_without_an_image_is_an_error() -> None:
    trk = BoTSORT.from_config(TrackerConfig())
    assert trk.cmc is not None
    with pytest.raises(FrameError, match="no image"):
        trk.update([det(100, 100)])
    assert BoTSORT.from_config(TrackerConfig(cmc_method="none")).cmc is None


def test_buffer_scales_with_frame_rate() -> None:
    assert BoTSORT.from_config(TrackerConfig(frame_rate_hz=15.0, track_buffer_frames=30)).max_time_lost == 15
    assert BoTSORT.from_config(TrackerConfig(frame_rate_hz=30.0, track_buffer_frames=30)).max_time_lost == 30


class _ColourEmbedding:
    """Appearance hook for the test: the embedding is looked up from a per-frame table."""

    def __init__(self) -> None:
        self.table: list[np.ndarray] = []
        self.calls = 0

    def __call__(self, image_rgb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        self.calls += 1
        assert len(self.table) == len(boxes)
        return np.array(self.table, dtype=np.float32)


def test_appearance_hook_resolves_an_ambiguous_assignment() -> None:
    # Two overlapping chairs A (left) and B (right). In the last frame the detections move so
    # that IoU alone prefers the crossed assignment; appearance says otherwise.
    img = np.zeros((480, 640, 3), np.uint8)
    a_feat, b_feat = np.array([1.0, 0.0]), np.array([0.0, 1.0])

    def run(use_appearance: bool) -> float:
        enc = _ColourEmbedding()
        trk = tracker(appearance=enc if use_appearance else None, fuse_score=False)
        box_a, box_b = (0.0, 0.0, 100.0, 100.0), (50.0, 0.0, 150.0, 100.0)
        for _ in range(6):
            enc.table = [a_feat, b_feat]
            out = trk.update([Detection(box_a, 0.9, "chair"), Detection(box_b, 0.9, "chair")], img)
        id_a = next(t.track_id for t in out if t.xyxy_px[0] < 25)
        enc.table = [a_feat, b_feat]
        out = trk.update([Detection((30.0, 0.0, 130.0, 100.0), 0.9, "chair"),
                          Detection((20.0, 0.0, 120.0, 100.0), 0.9, "chair")], img)
        if use_appearance:
            assert enc.calls == 7
        return centre(next(t for t in out if t.track_id == id_a))[0]

    # A follows the detection centred at 80 with appearance, the one at 70 without.
    assert run(True) > run(False) + 3.0


# --- SORT baseline -----------------------------------------------------------------------

def test_sort_reports_after_min_hits_and_keeps_the_id() -> None:
    trk = SORT(max_age=1, min_hits=3)
    outs = [trk.update([det(100 + 5 * k, 200)]) for k in range(10)]
    assert all(o[0].track_id == 1 for o in outs)  # first min_hits frames are reported too
    trk.update([])
    trk.update([])
    out = [trk.update([det(200, 200)]) for _ in range(4)]
    # Born with no hits; three consecutive updates follow before it is reported.
    assert out[:3] == [[], [], []] and out[3][0].track_id == 2


def test_degenerate_detections_are_ignored_not_fatal() -> None:
    trk = tracker()
    bad = [Detection((10.0, 10.0, 10.0, 50.0), 0.9, "chair"),
           Detection((float("nan"), 0.0, 5.0, 5.0), 0.9, "chair")]
    for k in range(5):
        out = trk.update([det(100 + k, 100), *bad])
    assert [t.track_id for t in out] == [1]

