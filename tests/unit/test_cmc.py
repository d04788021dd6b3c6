"""Camera-motion compensation on a real photograph warped by known motions."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.errors import FrameError
from semmap.tracking.cmc import IDENTITY, SparseFlowCMC


@pytest.fixture(scope="module")
def room_rgb(real_data: Path) -> np.ndarray:
    bgr = cv2.imread(str(real_data / "rgbd" / "diningroom" / "color" / "1.png"))
    assert bgr is not None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def warp(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    return cv2.warpAffine(img, A, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)


def rotation_about(deg: float, centre: tuple[float, float], t: tuple[float, float]) -> np.ndarray:
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = np.asarray(centre)
    return np.hstack([R, (c - R @ c + np.asarray(t))[:, None]])


PTS = np.array([[0, 0], [639, 0], [0, 479], [639, 479], [320, 240]], float)


def moved(H: np.ndarray, pts: np.ndarray = PTS) -> np.ndarray:
    """(N, 2) points mapped through a (3, 3) or (2, 3) motion."""
    H3 = np.vstack([H, [0.0, 0.0, 1.0]]) if H.shape == (2, 3) else H
    p = np.column_stack([pts, np.ones(len(pts))]) @ H3.T
    return p[:, :2] / p[:, 2:3]


@pytest.mark.parametrize("model", ["homography", "affine"])
@pytest.mark.parametrize("downscale", [1, 2])
@pytest.mark.parametrize(("deg", "t"), [(0.0, (14.0, -6.0)), (2.0, (-25.0, 3.0)), (-1.0, (0.0, 0.0))])
def test_recovers_a_known_image_motion(room_rgb, model, downscale, deg, t) -> None:
    A = rotation_about(deg, (320.0, 240.0), t)
    cmc = SparseFlowCMC(downscale=downscale, model=model)
    np.testing.assert_array_equal(cmc.apply(room_rgb), IDENTITY)  # first frame: nothing to compare
    W = cmc.apply(warp(room_rgb, A))
    assert W.shape == (3, 3)
    assert cmc.last_inliers >= 20
    # Compare where it matters: how the estimate moves points across the image.
    assert np.linalg.norm(moved(W) - moved(A), axis=1).max() < 0.6


def test_homography_follows_a_camera_yaw_that_an_affine_cannot(room_rgb) -> None:
    # A camera rotating 4 deg about its vertical axis (60 deg/s at 15 Hz) with an 80 deg field
    # of view: the image moves by K R K^-1, 1.7x more at the edges than in the centre.
    K = np.array([[383.0, 0.0, 320.0], [0.0, 383.0, 240.0], [0.0, 0.0, 1.0]])
    a = np.deg2rad(4.0)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    H = K @ R @ np.linalg.inv(K)
    H /= H[2, 2]
    nxt = cv2.warpPerspective(room_rgb, H, (640, 480), borderMode=cv2.BORDER_REFLECT)
    grid = np.array([[u, v] for u in np.linspace(20, 620, 7) for v in np.linspace(20, 460, 5)])
    errors = {}
    for model in ("homography", "affine"):
        cmc = SparseFlowCMC(model=model)
        cmc.apply(room_rgb)
        W = cmc.apply(nxt)
        errors[model] = np.linalg.norm(moved(W, grid) - moved(H, grid), axis=1).max()
    assert errors["homography"] < 1.0
    assert errors["affine"] > 2.0 * errors["homography"]


def test_objects_are_masked_out(room_rgb) -> None:
    # A big, strongly textured object moves 30 px left while the camera moves (10, 4).
    # Its corners outnumber the background's: unmasked, RANSAC would follow the object.
    rng = np.random.default_rng(0)
    patch = cv2.resize(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8), (320, 240),
                       interpolation=cv2.INTER_NEAREST)
    A = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 4.0]])
    f1, f2 = room_rgb.copy(), warp(room_rgb, A)
    f1[100:340, 100:420] = patch
    f2[100:340, 70:390] = patch
    estimates = {}
    for masked in (False, True):
        cmc = SparseFlowCMC()
        cmc.apply(f1, [(100, 100, 420, 340)] if masked else [])
        estimates[masked] = cmc.apply(f2, [(70, 100, 390, 340)])
    np.testing.assert_allclose(moved(estimates[True]), moved(A), atol=0.3)
    assert abs(moved(estimates[False])[4, 0] - 330.0) > 20.0  # the centre followed the object


def test_featureless_frames_give_the_identity() -> None:
    cmc = SparseFlowCMC()
    blank = np.full((480, 640, 3), 128, np.uint8)
    cmc.apply(blank)
    np.testing.assert_array_equal(cmc.apply(blank), IDENTITY)
    assert cmc.last_inliers == 0


def test_size_change_resets_instead_of_failing(room_rgb) -> None:
    cmc = SparseFlowCMC()
    cmc.apply(room_rgb)
    np.testing.assert_array_equal(cmc.apply(cv2.resize(room_rgb, (320, 240))), IDENTITY)


def test_bad_image_is_a_frame_error() -> None:
    with pytest.raises(FrameError, match="RGB"):
        SparseFlowCMC().apply(np.zeros((10, 10, 4), np.uint8))


def test_unknown_model_is_rejected() -> None:
    with pytest.raises(ValueError, match="homography"):
        SparseFlowCMC(model="similarity")  # type: ignore[arg-type]


def test_features_in_one_corner_fall_back_to_the_similarity() -> None:
    # Texture only in a 120x90 corner: a homography fitted there would extrapolate its
    # perspective terms over the whole image, so the constrained similarity is used.
    rng = np.random.default_rng(1)
    f1 = np.full((480, 640, 3), 128, np.uint8)
    f1[20:110, 20:140] = cv2.resize(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8), (120, 90),
                                    interpolation=cv2.INTER_NEAREST)
    A = np.array([[1.0, 0.0, 6.0], [0.0, 1.0, 4.0]])
    cmc = SparseFlowCMC(model="homography")
    cmc.apply(f1)
    W = cmc.apply(warp(f1, A))
    np.testing.assert_array_equal(W[2], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(moved(W), moved(A), atol=0.5)
