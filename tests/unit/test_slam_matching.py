"""Scan matchers, refinement, degeneracy and the pose graph on synthetic 2D worlds."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _slam_world import cast, corridor_world, room_world
from hypothesis import given, settings
from hypothesis import strategies as st

from semmap.config import SlamConfig
from semmap.errors import MapError
from semmap.grid import GridSpec
from semmap.occupancy import ProbabilityGrid
from semmap.scan import BandScan
from semmap.slam.correlative import BranchAndBoundMatcher, MatchGrid, real_time_correlative_match
from semmap.slam.local import LocalSlam, SlamStatus, constrained_translation
from semmap.slam.pose2d import compose, inverse, pose2, relative, transform_scan, transform_xy, wrap
from semmap.slam.pose_graph import Edge, optimize
from semmap.slam.refine import refine_pose

finite = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(finite, finite, angle, finite, finite, angle)
def test_pose2_compose_inverse_relative(x1: float, y1: float, a1: float, x2: float, y2: float, a2: float) -> None:
    a, b = pose2(x1, y1, a1), pose2(x2, y2, a2)
    np.testing.assert_allclose(compose(a, inverse(a))[:2], 0.0, atol=1e-9)
    assert abs(float(wrap(compose(a, inverse(a))[2]))) < 1e-9
    back = compose(a, relative(a, b))
    np.testing.assert_allclose(back[:2], b[:2], atol=1e-8)
    assert abs(float(wrap(back[2] - b[2]))) < 1e-9
    pts = np.array([[1.0, 2.0], [-3.0, 0.5]])
    np.testing.assert_allclose(transform_xy(compose(a, b), pts), transform_xy(a, transform_xy(b, pts)), atol=1e-8)


def test_transform_scan_moves_every_ray_and_keeps_the_rest() -> None:
    scan = BandScan.from_points(np.array([[1.0, 0.0], [1.0, 0.5], [2.0, -1.0]]), stamp_s=3.5)
    p = pose2(2.0, -1.0, 0.7)
    moved = transform_scan(p, scan)
    np.testing.assert_allclose(moved.origin_xy_m, transform_xy(p, scan.origin_xy_m)[0])
    for name in ("near_xy_m", "far_xy_m", "hit_xy_m"):
        np.testing.assert_allclose(getattr(moved, name), transform_xy(p, getattr(scan, name)))
    assert moved.stamp_s == 3.5 and moved.band == scan.band
    np.testing.assert_array_equal(moved.is_hit, scan.is_hit)
    np.testing.assert_array_equal(moved.valid, scan.valid)
    np.testing.assert_allclose(moved.hits_xy_m, transform_xy(p, scan.hits_xy_m))


def _hits(poses: list[np.ndarray], world: list) -> np.ndarray:
    return np.concatenate([transform_xy(p, cast(world, p, fov_deg=360.0, n_rays=720)) for p in poses])


@pytest.fixture(scope="module")
def room_grid() -> MatchGrid:
    spec = GridSpec.covering(-1.0, -1.0, 9.0, 7.0, 0.05)
    return MatchGrid.from_hits(_hits([pose2(2.0, 1.5, 0.0), pose2(6.0, 4.5, 2.0), pose2(4.0, 3.0, -1.0)], room_world()),
                               spec, 0.05)


def test_probability_likelihood_field_peaks_on_occupied_cells() -> None:
    spec = GridSpec.covering(-1.0, -1.0, 9.0, 7.0, 0.05)
    grid = ProbabilityGrid(spec)
    p = pose2(2.0, 1.5, 0.3)
    r = transform_scan(p, BandScan.from_points(cast(room_world(), p, fov_deg=360.0, n_rays=720)))
    for _ in range(3):
        grid.insert_scan(r.origin_xy_m, r.near_xy_m, r.far_xy_m, r.hit_xy_m, r.is_hit, r.valid)
    field = MatchGrid.likelihood_field(grid, 0.05)
    occ = grid.probability() > 0.5
    assert np.all(field.probability[occ] == pytest.approx(1.0))
    assert float(field.probability[grid.known & ~occ].mean()) < 0.3


def test_correlative_then_refine_recovers_an_offset(room_grid: MatchGrid) -> None:
    truth = pose2(3.6, 2.7, 0.4)
    pts = cast(room_world(), truth, rng=np.random.default_rng(1), noise_m=0.01)
    start = compose(truth, pose2(0.07, -0.06, math.radians(3.0)))
    rt, score = real_time_correlative_match(room_grid, pts, start, 0.12, math.radians(5.0), 0.1, 0.1)
    assert score > 0.6
    ref = refine_pose(room_grid, pts, rt, translation_weight=0.0, rotation_weight=0.0)
    assert np.hypot(*(ref.pose[:2] - truth[:2])) < 0.04
    assert abs(math.degrees(float(wrap(ref.pose[2] - truth[2])))) < 0.5
    lo, hi = ref.translation_eigenvalues()
    assert lo > 0.05 * hi


def test_branch_and_bound_finds_the_exhaustive_optimum(room_grid: MatchGrid) -> None:
    truth = pose2(5.0, 2.2, 2.5)
    pts = cast(room_world(), truth)
    start = compose(truth, pose2(-0.35, 0.3, math.radians(-7.0)))
    bbs = BranchAndBoundMatcher(room_grid, depth=5)
    hit = bbs.match(pts, start, 0.5, math.radians(10.0), min_score=0.5)
    assert hit is not None
    pose, score = hit
    # The exhaustive search over the same window and angles agrees.
    ex, ex_score = real_time_correlative_match(room_grid, pts, start, 0.5, math.radians(10.0), 0.0, 0.0)
    assert score == pytest.approx(ex_score, abs=1e-6)
    assert np.hypot(*(pose[:2] - truth[:2])) < 0.06
    # Nothing scores that well far from the truth.
    assert bbs.match(pts, start, 0.5, math.radians(10.0), min_score=min(0.999, score + 0.01)) is None


def test_corridor_takes_only_the_along_corridor_direction_from_odometry() -> None:
    # Odometry reads 3 % long along the corridor and jumps 5 cm sideways at scan 5. The walls
    # pin y (across) but not x (along): x follows the odometry, y is pulled back to the truth.
    cfg = SlamConfig(motion_filter_distance_m=0.05)
    local = LocalSlam(cfg)
    world = corridor_world()
    for i in range(30):
        truth = pose2(0.1 * i, 1.0, 0.0)
        odom = pose2(0.1 * i * 1.03, 1.0 + (0.05 if i >= 5 else 0.0), 0.0)
        # Looking along the corridor at a slant: both walls, nothing across.
        pts = cast(world, compose(truth, pose2(0, 0, 0.0)), fov_deg=80.0, max_range_m=6.0)
        res = local.add_scan(0.1 * i, BandScan.from_points(pts), odom)
        if i > 2:
            assert res.status is SlamStatus.PARTIAL_ODOMETRY, res.reason
            assert "unconstrained" in res.reason
            assert res.pose_local[0] == pytest.approx(res.prediction_local[0], abs=0.02)
    assert abs(res.pose_local[1] - 1.0) < 0.02  # the 5 cm jump is mostly undone
    assert res.pose_local[0] == pytest.approx(0.1 * 29 * 1.03, abs=0.03)  # along: the odometry's


def test_one_wall_in_view_is_matched_across_it() -> None:
    # A narrow view of one long wall (as a camera close to a wall sees it): before the per-
    # direction test this was a whole odometry fallback; now only the along-wall direction is.
    cfg = SlamConfig(motion_filter_distance_m=0.05)
    local = LocalSlam(cfg)
    wall = [(-30.0, 2.0, 30.0, 2.0)]
    statuses = []
    for i in range(16):
        truth = pose2(0.05 * i, 0.0, math.pi / 2)  # facing the wall at y = 2
        odom = pose2(0.05 * i * 1.05, 0.0, math.pi / 2)  # reads 5 % long along the wall
        res = local.add_scan(0.2 * i, BandScan.from_points(cast(wall, truth, fov_deg=60.0)), odom)
        statuses.append(res.status)
        if i > 2:
            assert res.pose_local[0] == pytest.approx(res.prediction_local[0], abs=0.01)  # along: odometry
            # Across: matched (one wall holds yaw only softly, so this slowly degrades over
            # a long run along a featureless wall; loop closure is what bounds it).
            assert abs(res.pose_local[1]) < 0.03
    assert SlamStatus.DEGENERATE_FALLBACK_ODOMETRY not in statuses[3:]
    assert statuses.count(SlamStatus.PARTIAL_ODOMETRY) >= 12


def test_no_structure_at_all_is_a_full_fallback() -> None:
    info = np.diag([0.5, 0.2, 3.0])
    xy, free = constrained_translation(info, np.array([1.0, 2.0]), np.array([1.1, 2.1]), 10.0, 0.1)
    assert xy is None and free is None


def test_well_constrained_match_is_kept_whole() -> None:
    info = np.diag([400.0, 250.0, 50.0])
    xy, free = constrained_translation(info, np.array([1.0, 2.0]), np.array([1.1, 2.1]), 10.0, 0.1)
    assert free is None
    np.testing.assert_allclose(xy, [1.0, 2.0])


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, math.pi), st.floats(20.0, 2000.0), st.floats(0.0, 5.0),
       finite, finite, st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_per_direction_split(wall_angle: float, strong: float, weak: float, mx: float, my: float,
                             dx: float, dy: float) -> None:
    # Information of a wall whose normal is at wall_angle: strong across it, weak along it.
    n = np.array([math.cos(wall_angle), math.sin(wall_angle)])
    t = np.array([-n[1], n[0]])
    info = np.zeros((3, 3))
    info[:2, :2] = strong * np.outer(n, n) + weak * np.outer(t, t)
    matched = np.array([mx, my])
    pred = matched + np.array([dx, dy])
    xy, free = constrained_translation(info, matched, pred, 10.0, 0.1)
    assert xy is not None and free is not None
    # Across the wall: the match; along it: the prediction.
    assert float(n @ xy) == pytest.approx(float(n @ matched), abs=1e-9)
    assert float(t @ xy) == pytest.approx(float(t @ pred), abs=1e-9)
    assert abs(float(free @ t)) == pytest.approx(1.0, abs=1e-9)


def test_pose_graph_closes_a_loop_with_a_robust_loss() -> None:
    # A square of 40 nodes with odometry that under-turns; one true loop closure and one
    # wrong one (robust): the loop closes and the wrong closure does not drag the map.
    n = 40
    truth = []
    for i in range(n):
        side, f = divmod(i, 10)
        corners = [(0, 0), (4, 0), (4, 4), (0, 4), (0, 0)]
        a, b = np.array(corners[side]), np.array(corners[side + 1])
        p = a + (b - a) * f / 10
        truth.append(pose2(p[0], p[1], side * math.pi / 2))
    odo = [truth[0]]
    edges = []
    for i in range(1, n):
        z = relative(truth[i - 1], truth[i]) + np.array([0.0, 0.0, math.radians(-1.0)])
        odo.append(compose(odo[-1], z))
        edges.append(Edge(i - 1, i, tuple(z), 100.0, 100.0))
    edges.append(Edge(0, n - 1, tuple(relative(truth[0], truth[n - 1])), 100.0, 100.0, robust=True))
    edges.append(Edge(5, 25, (3.0, -1.0, 1.0), 100.0, 100.0, robust=True))
    before = np.mean([np.hypot(*(o[:2] - t[:2])) for o, t in zip(odo, truth, strict=True)])
    res = optimize(np.array(odo), edges, n_fixed=1, huber_scale=1.0, max_iterations=50)
    after = np.mean([np.hypot(*(o[:2] - t[:2])) for o, t in zip(res.poses, truth, strict=True)])
    assert res.cost_final < res.cost_initial
    assert after < 0.5 * before
    with pytest.raises(MapError):
        optimize(np.array(odo), [Edge(0, n + 3, (0.0, 0.0, 0.0), 1.0, 1.0)])
