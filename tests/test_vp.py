"""Tests of rescu.scene.vp: RP-based VPD, the LSD baseline, the angular constraint, VP errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rescu import layout as L
from rescu.scene.vp.errors import closest_gt_error, point_error, success_rate, vector_error
from rescu.evaluation.vpd import paired_test
from rescu.scene.vp.estimator import (joint_vanishing_point, rp_vanishing_point,
                                      union_vanishing_point)
from rescu.scene.vp.geometry import _normaliser, ac_mask
from rescu.scene.vp.lines import Lines, pattern_lines
from rescu.scene.vp.lsd import line_vanishing_point
from rescu.scene.vp.params import VPParams
from rescu.scene.vp.ransac import ransac_vp
from rescu.scene.vp.refine import _track_costs, _track_scatter, ml_refine_vp, spacing_refine_vp

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

# visual words: 4 corners, the centre and an off-centre point of a unit-ish square
WORDS = np.array([[0, 0], [0.6, 0], [0.6, 0.6], [0, 0.6], [0.3, 0.3], [0.18, 0.42]])


def project(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ h.T
    return q[:, :2] / q[:, 2:]


def grid(h: np.ndarray, nx: int, ny: int, noise: float = 0.0, seed: int = 0,
         xs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N, 4) and feature points (M, N, 2) of squares at (x, j) on a plane seen by h.

    Instance n = j * nx + i (row j, column i); the row direction is the plane's X axis.
    """
    rng = np.random.default_rng(seed)
    xs = np.arange(nx, dtype=float) if xs is None else np.asarray(xs, float)
    boxes, fps = [], []
    for j in range(ny):
        for x in xs:
            ph = project(h, WORDS + [x, j])
            ph = ph + rng.normal(0.0, noise, ph.shape)
            q = ph[:4]
            boxes.append([q[:, 0].min(), q[:, 1].min(), np.ptp(q[:, 0]), np.ptp(q[:, 1])])
            fps.append(ph)
    return np.array(boxes), np.transpose(np.array(fps), (1, 0, 2))


H_PERSP = np.array([[60.0, 5, 100], [2, 60, 150], [0.08, 0.005, 1.0]])
H_FRONTAL = np.array([[60.0, 0, 100], [0, 60, 150], [0, 0, 1.0]])
SIZE = (640, 480)


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


# ----------------------------------------------------------------------------- params
def test_params_from_dict_rejects_unknown_key():
    assert VPParams.from_dict({"inlier_angle_deg": 2.0}).inlier_angle_deg == 2.0
    with pytest.raises(ValueError, match="bogus"):
        VPParams.from_dict({"bogus": 1})
    with pytest.raises(ValueError, match="min_lines"):
        VPParams(min_lines=1)


# ----------------------------------------------------------------------------- rows
def test_group_rows_wide_grid_gives_rows_in_order():
    b, _ = grid(H_FRONTAL, nx=5, ny=3)
    c, sz = L.instance_centres_sizes(b)
    rows = L.group_rows(c, sz)
    assert sorted(r.tolist() for r in rows) == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9],
                                                [10, 11, 12, 13, 14]]


def test_group_rows_tall_grid_gives_columns_no_diagonals():
    b, _ = grid(H_FRONTAL, nx=3, ny=5)
    c, sz = L.instance_centres_sizes(b)
    rows = L.group_rows(c, sz)
    assert sorted(r.tolist() for r in rows) == [[0, 3, 6, 9, 12], [1, 4, 7, 10, 13],
                                                [2, 5, 8, 11, 14]]


def test_group_rows_square_grid_prefers_horizontal_rows():
    b, _ = grid(H_FRONTAL, nx=4, ny=4)
    c, sz = L.instance_centres_sizes(b)
    rows = L.group_rows(c, sz)
    assert sorted(r.tolist() for r in rows) == [[4 * j + i for i in range(4)]
                                                for j in range(4)]


def test_group_rows_two_instances_is_one_row_and_scatter_is_none():
    c = np.array([[10.0, 10], [50, 12]])
    assert [r.tolist() for r in L.group_rows(c, np.array([5.0, 5]))] == [[0, 1]]
    tri = np.array([[0.0, 0], [100, 0], [50, 80]])
    assert L.group_rows(tri, np.full(3, 10.0)) == []


def test_group_rows_bad_shape_names_argument():
    with pytest.raises(ValueError, match="centres"):
        L.group_rows(np.zeros((3, 3)), np.ones(3))


# ----------------------------------------------------------------------------- VPD
@pytest.mark.parametrize("seed", range(5))
def test_rp_vp_recovers_finite_vp_under_noise(seed):
    b, fp = grid(H_PERSP, nx=6, ny=3, noise=1.0, seed=seed)
    vp, rows = rp_vanishing_point(b, fp, SIZE)
    gt = unit(H_PERSP @ [1.0, 0, 0])
    assert vp is not None and len(rows) == 3
    assert vector_error(vp.homogeneous, gt, SIZE) < 1.5
    assert vp.support >= 15
    assert np.isclose(np.linalg.norm(vp.homogeneous), 1.0)
    assert vp.inside_image is False


def test_rp_vp_exact_without_noise():
    b, fp = grid(H_PERSP, nx=6, ny=2)
    vp, _ = rp_vanishing_point(b, fp, SIZE)
    gt = unit(H_PERSP @ [1.0, 0, 0])
    assert point_error(vp.homogeneous, gt) < 1e-6 * np.linalg.norm(gt[:2] / gt[2])


def test_frontal_row_vp_at_infinity():
    b, fp = grid(H_FRONTAL, nx=5, ny=1, noise=0.5, seed=3)
    vp, rows = rp_vanishing_point(b, fp, SIZE)
    assert [r.tolist() for r in rows] == [[0, 1, 2, 3, 4]]
    assert vp is not None and vp.homogeneous[2] == 0.0 and not vp.inside_image
    assert abs(vp.homogeneous[1]) < np.sin(np.radians(1.0))


def test_exactly_parallel_lines_give_infinity_and_ac_blocks_their_pairs():
    lines = Lines(np.array([[0.0, 0], [0, 10], [0, 20]]), np.tile([1.0, 0.0], (3, 1)),
                    np.ones(3))
    vp = ransac_vp(lines, (100, 100))
    assert vp is not None
    np.testing.assert_allclose(vp.homogeneous, [1.0, 0.0, 0.0], atol=1e-12)
    assert vp.support == 3


def test_angular_constraint_rejects_near_parallel_pairs():
    a = np.array([[1.0, 0.0]] * 3)
    ang = np.radians([1.0, 1.99, 2.01])
    b = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    assert ac_mask(a, b, 2.0).tolist() == [False, False, True]
    assert ac_mask(a, -b, 2.0).tolist() == [False, False, True]  # orientation-free


def test_ac_keeps_outlier_pair_from_hypothesising():
    # two nearly parallel outlier lines would meet at a spurious point; the three
    # inliers meet at (500, 0)
    p = np.array([500.0, 0.0])
    mids = np.array([[0.0, 0], [0, 100], [0, 200]])
    dirs = p - mids
    lines = Lines(mids, dirs, np.ones(3))
    vp = ransac_vp(lines, (200, 200), VPParams(infinity_alpha=0))
    assert point_error(vp.homogeneous, np.array([500.0, 0, 1])) < 1e-6


def test_too_few_lines_none():
    assert ransac_vp(Lines.empty(), (10, 10)) is None
    one = Lines(np.zeros((1, 2)), np.array([[1.0, 0]]), np.ones(1))
    assert ransac_vp(one, (10, 10)) is None
    b = np.array([[0.0, 0, 10, 10]])
    assert rp_vanishing_point(b, None, (100, 100)) == (None, [])


def test_rp_vp_without_features_uses_box_centres():
    b, _ = grid(H_PERSP, nx=6, ny=3)
    vp, rows = rp_vanishing_point(b, None, SIZE)
    gt = unit(H_PERSP @ [1.0, 0, 0])
    assert vp is not None and vp.support == 3
    assert vector_error(vp.homogeneous, gt, SIZE) < 2.0


def test_deterministic():
    b, fp = grid(H_PERSP, nx=7, ny=4, noise=1.0)
    p = VPParams(ransac_iterations=50, seed=7)
    v1, _ = rp_vanishing_point(b, fp, SIZE, p)
    v2, _ = rp_vanishing_point(b, fp, SIZE, p)
    assert np.array_equal(v1.homogeneous, v2.homogeneous) and v1.support == v2.support


@settings(max_examples=40, deadline=None)
@given(x=st.floats(-3000, 3000), y=st.floats(-3000, 3000),
       seed=st.integers(0, 2 ** 16))
def test_ransac_recovers_random_finite_vp(x, y, seed):
    rng = np.random.default_rng(seed)
    vp_true = np.array([x, y, 1.0])
    mids = rng.uniform([50, 50], [590, 430], (12, 2))
    if np.min(np.linalg.norm(mids - [x, y], axis=1)) < 150:
        return  # VP on top of the segments: ill-posed
    dirs = np.array([x, y]) - mids
    # 0.5 px noise on the ends of 200 px segments
    ends = np.concatenate([mids - 100 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True),
                           mids + 100 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)],
                          axis=1) + rng.normal(0, 0.5, (12, 4))
    vp = ransac_vp(Lines.from_segments(ends), SIZE)
    assert vp is not None
    assert vector_error(vp.homogeneous, vp_true, SIZE) < 1.0


@settings(max_examples=30, deadline=None)
@given(theta=st.floats(0, np.pi), seed=st.integers(0, 2 ** 16))
def test_ransac_recovers_vp_at_infinity(theta, seed):
    rng = np.random.default_rng(seed)
    d = np.array([np.cos(theta), np.sin(theta)])
    mids = rng.uniform([50, 50], [590, 430], (10, 2))
    ends = np.concatenate([mids - 100 * d, mids + 100 * d], axis=1) + rng.normal(0, 0.3,
                                                                                (10, 4))
    vp = ransac_vp(Lines.from_segments(ends), SIZE)
    assert vp is not None
    assert vector_error(vp.homogeneous, np.array([d[0], d[1], 0.0]), SIZE) < 0.5


# ----------------------------------------------------------------------------- baseline
def test_lsd_baseline_finds_drawn_vp():
    import cv2

    img = np.full((240, 320), 255, np.uint8)
    vp_true = np.array([700.0, 100.0])
    for y0 in range(20, 230, 25):
        p0 = np.array([10.0, y0])
        p1 = p0 + 0.5 * (vp_true - p0)
        cv2.line(img, tuple(int(v) for v in p0), tuple(int(v) for v in p1), 0, 2,
                 cv2.LINE_AA)
    rgb = np.repeat(img[:, :, None], 3, axis=2)
    vp = line_vanishing_point(rgb, VPParams())
    assert vp is not None
    assert vector_error(vp.homogeneous, np.r_[vp_true, 1.0], (320, 240)) < 2.0
    # a downscaled copy gives the VP in original pixels
    small = cv2.resize(rgb, (160, 120), interpolation=cv2.INTER_AREA)
    vp2 = line_vanishing_point(small, VPParams(), scale_factor=0.5)
    assert vp2 is not None
    assert vector_error(vp2.homogeneous, np.r_[vp_true, 1.0], (320, 240)) < 3.0


def test_lsd_blank_image_no_vp():
    assert line_vanishing_point(np.zeros((50, 60, 3), np.uint8)) is None


# ----------------------------------------------------------------------------- errors
def test_point_error_cases():
    a = np.array([3.0, 4.0, 1.0])
    assert point_error(a, np.array([0.0, 0, 1])) == pytest.approx(5.0)
    assert point_error(2 * a, -a) == pytest.approx(0.0)
    assert point_error(a, np.array([1.0, 0, 0])) == np.inf
    assert point_error(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0])) == 0.0
    assert point_error(np.array([1.0, 0, 0]), np.array([0.0, 1, 0])) == np.inf


def test_vector_error_known_values():
    size = (400, 400)  # centre (200, 200), f = 200
    # VP at the centre -> direction (0, 0, 1); VP at infinity along x -> (1, 0, 0)
    assert vector_error(np.array([200.0, 200, 1]), np.array([1.0, 0, 0]), size) == \
        pytest.approx(90.0)
    # (400, 200) -> (200, 0, 200): 45 degrees from the optical axis
    assert vector_error(np.array([400.0, 200, 1]), np.array([200.0, 200, 1]), size) == \
        pytest.approx(45.0)
    # true focal / principal point
    assert vector_error(np.array([100.0, 0, 1]), np.array([0.0, 0, 1]), size, focal=100,
                          principal_point=(0, 0)) == pytest.approx(45.0)
    # antipodal directions are the same VP
    assert vector_error(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]), size) == 0.0
    # continuity at infinity: a point 1e9 px away vs the point at infinity
    assert vector_error(np.array([1e9, 200, 1]), np.array([1.0, 0, 0]), size) == \
        pytest.approx(np.degrees(np.arctan2(200.0, 1e9 - 200.0)), rel=1e-9)


def test_closest_gt_error_takes_min():
    gts = [np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), np.array([200.0, 200, 1])]
    e = closest_gt_error(np.array([0.0, 1, 0]), gts, "vector", (400, 400))
    assert e == 0.0
    assert np.isnan(closest_gt_error(np.array([0.0, 1, 0]), [], "vector", (4, 4)))
    with pytest.raises(ValueError, match="kind"):
        closest_gt_error(np.zeros(3), gts, "angle", (4, 4))


def test_success_rate_and_paired_test():
    e = [0.5, 1.0, 2.0, np.inf, np.nan]
    np.testing.assert_allclose(success_rate(e, [0.5, 1.0, 5.0]), [0.2, 0.4, 0.6])
    assert np.isnan(success_rate([], [1.0])).all()
    assert paired_test([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 1.0
    assert paired_test([], []) == 1.0
    a = np.linspace(0.1, 1.0, 20)
    assert paired_test(a, a + 1.0) < 0.001
    # infinite (missing) errors are ranked last, not dropped
    assert paired_test(a, np.full(20, np.inf)) < 0.001
    with pytest.raises(ValueError, match="same length"):
        paired_test([1.0], [1.0, 2.0])


@pytest.mark.skipif(not (SHARED / "york_urban").is_dir(), reason="../shared/data absent")
def test_lsd_baseline_on_one_york_urban_image():
    from rescu import io

    gt = io.load_vanishing_points(SHARED / "york_urban" / "vanishing_points.json")
    name = sorted(gt)[0]
    im = io.load_image(SHARED / "york_urban" / name)
    vp = line_vanishing_point(im.rgb, VPParams(), im.scale_factor)
    assert vp is not None and np.isclose(np.linalg.norm(vp.homogeneous), 1.0)


def test_group_rows_prefers_horizontal_rows_over_slightly_tighter_columns():
    # 3 x 3 grid, column pitch 0.85 x the row pitch: still rows (no diagonals)
    c = np.array([[100.0 * i, 85.0 * j] for j in range(3) for i in range(3)])
    rows = L.group_rows(c, np.full(9, 40.0))
    assert sorted(r.tolist() for r in rows) == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    # columns twice as tight: columns
    c2 = np.array([[100.0 * i, 45.0 * j] for j in range(3) for i in range(3)])
    rows2 = L.group_rows(c2, np.full(9, 30.0))
    assert sorted(r.tolist() for r in rows2) == [[0, 3, 6], [1, 4, 7], [2, 5, 8]]


# ----------------------------------------------------------------------------- ML, spacing, joint
def _norm_tracks(fp: np.ndarray, rows: list[list[int]], size=SIZE):
    """Feature tracks (one per word and row) in the normalised coordinates of ransac_vp,
    with the instance ordinals of their points."""
    t = _normaliser(size)
    pts, pos = [], []
    for r in rows:
        for m in range(fp.shape[0]):
            pts.append(fp[m, r] * t[0, 0] + t[:2, 2])
            pos.append(np.arange(len(r), dtype=float))
    return t, pts, pos


def test_ml_refine_exact_without_noise_from_a_perturbed_start():
    _, fp = grid(H_PERSP, nx=6, ny=2)
    t, pts, _ = _norm_tracks(fp, [list(range(6)), list(range(6, 12))])
    gt = unit(t @ (H_PERSP @ [1.0, 0, 0]))
    v = ml_refine_vp(pts, unit(gt + [0.01, -0.02, 0.0]))
    assert min(np.linalg.norm(v - gt), np.linalg.norm(v + gt)) < 1e-8


def test_track_costs_zero_on_the_line_and_continuous_at_infinity():
    q = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    scat, n = _track_scatter([q])
    assert n == 3
    assert _track_costs(np.array([5.0, 0.0, 1.0]), scat)[0] == pytest.approx(0.0, abs=1e-12)
    assert _track_costs(np.array([1.0, 0.0, 0.0]), scat)[0] == pytest.approx(0.0, abs=1e-12)
    # a line through (0, 1) and q's centroid direction: distances known
    c_far = _track_costs(np.array([1.0, 1e-9, 1e-12]), scat)[0]
    c_inf = _track_costs(np.array([1.0, 1e-9, 0.0]), scat)[0]
    assert c_far == pytest.approx(c_inf, abs=1e-12)


def test_ml_infinity_test_keeps_converging_row_and_snaps_frontal_one():
    # one row of five instances: 5 tracks of 5 points each (25 points), 0.5 px noise
    b, fp = grid(H_PERSP, nx=5, ny=1, noise=0.5, seed=1)
    vp, _ = rp_vanishing_point(b, fp, SIZE)
    assert vp.homogeneous[2] != 0
    assert vector_error(vp.homogeneous, unit(H_PERSP @ [1.0, 0, 0]), SIZE) < 2.0
    b, fp = grid(H_FRONTAL, nx=5, ny=1, noise=0.5, seed=1)
    vp, _ = rp_vanishing_point(b, fp, SIZE)
    assert vp.homogeneous[2] == 0


def test_spacing_model_beats_line_model_on_single_equal_rows():
    from functools import partial

    from rescu.scene.analyse import equal_rows
    from rescu.scene.symmetry import SymmetryParams

    gt = unit(H_PERSP @ [1.0, 0, 0])
    err_line, err_sp = [], []
    for seed in range(8):
        b, fp = grid(H_PERSP, nx=6, ny=1, noise=0.7, seed=seed)
        v_line, _ = rp_vanishing_point(b, fp, SIZE)
        row_test = partial(equal_rows, symmetry_params=SymmetryParams(), params=VPParams())
        v_sp, _ = rp_vanishing_point(b, fp, SIZE, VPParams(), row_test)
        err_line.append(vector_error(v_line.homogeneous, gt, SIZE))
        err_sp.append(vector_error(v_sp.homogeneous, gt, SIZE))
    assert np.mean(err_sp) < 0.5 * np.mean(err_line)
    assert max(err_sp) < 1.5 < max(err_line)


def test_spacing_model_exact_without_noise_and_rejected_on_unequal_rows():
    xs = np.array([0.0, 1.0, 2.5, 3.2, 5.0, 5.6])  # clearly unequal
    _, fp = grid(H_PERSP, nx=6, ny=1, xs=xs, noise=0.2, seed=2)
    t, pts, pos = _norm_tracks(fp, [list(range(6))])
    v0 = ml_refine_vp(pts, unit(t @ (H_PERSP @ [1.0, 0, 0])))
    assert spacing_refine_vp(pts, pos, v0, 0.01, 0.01, 0.25 * t[0, 0]) is None
    _, fp = grid(H_PERSP, nx=6, ny=1)
    t, pts, pos = _norm_tracks(fp, [list(range(6))])
    gt = unit(t @ (H_PERSP @ [1.0, 0, 0]))
    v = spacing_refine_vp(pts, pos, unit(gt + [0.02, 0.0, 0.0]), 0.01, 0.01, 1e-4)
    assert v is not None and min(np.linalg.norm(v - gt), np.linalg.norm(v + gt)) < 1e-7
    # a gap (missing feature) keeps the ordinals right
    pos[0] = np.array([0.0, 1, 3, 4, 5])
    pts[0] = np.delete(pts[0], 2, axis=0)
    v = spacing_refine_vp(pts, pos, unit(gt + [0.02, 0.0, 0.0]), 0.01, 0.01, 1e-4)
    assert v is not None and min(np.linalg.norm(v - gt), np.linalg.norm(v + gt)) < 1e-7


def test_joint_vp_merges_patterns_sharing_the_vp_only():
    p = VPParams(spacing_alpha=0)
    # dominant: one row; second: two rows of the same plane (same VP); third: another
    # direction (the plane's Y axis)
    b0, f0 = grid(H_PERSP, nx=5, ny=1, noise=0.5, seed=4)
    b1, f1 = grid(H_PERSP @ np.array([[1, 0, 0], [0, 1, 3.0], [0, 0, 1]]), nx=6, ny=2,
                  noise=0.5, seed=5)
    h2 = H_PERSP @ np.array([[0, 1, 8.0], [1, 0, 0], [0, 0, 1]])  # rows along plane Y
    b2, f2 = grid(h2, nx=5, ny=1, noise=0.5, seed=6)
    sets, vps = [], []
    for b, f in ((b0, f0), (b1, f1), (b2, f2)):
        vp, rows = rp_vanishing_point(b, f, SIZE, p)
        c, sz = L.instance_centres_sizes(b)
        sets.append(pattern_lines(f, c, rows, sz))
        vps.append(vp)
    vp, used = joint_vanishing_point(sets, vps, SIZE, p)
    assert used == [0, 1]
    gt = unit(H_PERSP @ [1.0, 0, 0])
    assert vector_error(vp.homogeneous, gt, SIZE) < vector_error(vps[0].homogeneous,
                                                                     gt, SIZE)
    assert vp.support == len(sets[0]) + len(sets[1])
    # off: the dominant VP unchanged
    vp_off, used_off = joint_vanishing_point(sets, vps, SIZE, VPParams(joint_alpha=0))
    assert used_off == [0] and np.array_equal(vp_off.homogeneous, vps[0].homogeneous)
    with pytest.raises(ValueError, match="same length"):
        joint_vanishing_point(sets, vps[:2], SIZE)


def _pattern(h: np.ndarray, nx: int, seed: int, words: list[int] | None = None,
             params: VPParams = VPParams(spacing_alpha=0)) -> tuple[Lines, object]:
    """One row of nx instances on the plane seen by h: its implicit lines and own VP."""
    b, f = grid(h, nx=nx, ny=1, noise=0.3, seed=seed)
    if words is not None:
        f = f[words]
    vp, rows = rp_vanishing_point(b, f, SIZE, params)
    c, sz = L.instance_centres_sizes(b)
    return pattern_lines(f, c, rows, sz), vp


def test_union_vp_finds_the_vp_of_patterns_too_small_for_their_own():
    p = VPParams(spacing_alpha=0)
    # two rows of one plane, two visual words each: 2 lines, fewer than min_lines = 3
    a, va = _pattern(H_PERSP, 5, 1, [0, 4])
    b, vb = _pattern(H_PERSP @ np.array([[1, 0, 0], [0, 1, 3.0], [0, 0, 1]]), 5, 2, [1, 5])
    assert va is None and vb is None and len(a) == len(b) == 2
    vp, refused = union_vanishing_point([a, b], [va, vb], SIZE, p)
    assert refused is None and vp.support == 4
    assert vector_error(vp.homogeneous, unit(H_PERSP @ [1.0, 0, 0]), SIZE) < 0.5
    assert union_vanishing_point([Lines.empty()], [None], SIZE, p) == (None, None)
    with pytest.raises(ValueError, match="same length"):
        union_vanishing_point([a, b], [va], SIZE, p)
    # equal votes instead of track lengths: the same VP here
    same, _ = union_vanishing_point([a, b], [va, vb], SIZE, p, [np.ones(2), np.ones(2)])
    np.testing.assert_allclose(same.homogeneous, vp.homogeneous, atol=1e-9)
    with pytest.raises(ValueError, match="one vote per line"):
        union_vanishing_point([a, b], [va, vb], SIZE, p, [np.ones(2), np.ones(3)])


def test_union_vp_refused_by_a_pattern_whose_own_vp_differs():
    p = VPParams(spacing_alpha=0)
    turn = 0.1  # radians: the second plane's rows point to another VP
    rot = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0],
                    [0, 0, 1]])
    a, va = _pattern(H_PERSP, 6, 1)
    b, vb = _pattern(H_PERSP @ np.array([[1, 0, 0], [0, 1, 1.5], [0, 0, 1]]) @ rot, 6, 2)
    assert va is not None and vb is not None
    vp, refused = union_vanishing_point([a, b], [va, vb], SIZE, p)
    assert vp is None and refused in (0, 1)
    # without the test (level 0) the union VP is kept, off both patterns' own VPs
    vp, refused = union_vanishing_point([a, b], [va, vb], SIZE,
                                        VPParams(spacing_alpha=0, joint_alpha=0))
    gt = unit(H_PERSP @ [1.0, 0, 0])
    assert refused is None and vp.support > max(len(a), len(b))  # rows of both
    assert vector_error(vp.homogeneous, gt, SIZE) > vector_error(va.homogeneous, gt, SIZE)


def test_new_params_validated():
    assert VPParams.from_dict({"ml_refine": False, "joint_alpha": 0.0,
                                 "spacing_alpha": 0.0, "infinity_noise_px": 0.5}).ml_refine is False
    for k, v in (("joint_alpha", 1.0), ("spacing_alpha", -0.1), ("infinity_noise_px", -1.0)):
        with pytest.raises(ValueError, match=k):
            VPParams(**{k: v})


def test_registered_centres_fix_a_partial_box_and_duplicates_leave_the_row():
    b, fp = grid(H_FRONTAL, nx=6, ny=1)
    c, sz = L.instance_centres_sizes(b)
    # instance 2 detected with only its left half: box shifted and smaller
    b2 = b.copy()
    b2[2, 2] /= 2
    c2, _ = L.instance_centres_sizes(b2)
    np.testing.assert_allclose(L.registered_centres(c2, fp), c, atol=1e-9)
    # a duplicate of instance 3 (same features, slightly shifted box): left out
    b3 = np.concatenate([b, b[3:4] + [2.0, 1.0, 0, 0]])
    fp3 = np.concatenate([fp, fp[:, 3:4]], axis=1)
    fp3[:2, 6] = np.nan  # fewer features than the original
    cen, _, rows = L.pattern_rows(b3, fp3, VPParams())
    assert [r.tolist() for r in rows] == [[0, 1, 2, 3, 4, 5]]
    assert L.duplicate_instances(cen, L.instance_centres_sizes(b3)[1], fp3).tolist() == \
        [False] * 6 + [True]
    # stage-II instances without features keep their box centres
    np.testing.assert_array_equal(L.registered_centres(c, fp[:, :4])[4:], c[4:])
    np.testing.assert_array_equal(L.registered_centres(c, None), c)


def test_quantiles_are_scipy_stats():
    from scipy.stats import chi2, f

    from rescu.scene.vp.geometry import _chi2_ppf, _f_ppf

    for q in (0.8, 0.95, 0.99, 0.999, 0.9999):
        for d in (1, 2, 3, 7, 40):
            assert _chi2_ppf(q, d) == chi2.ppf(q, d)
            for d2 in (1, 2, 5, 100):
                assert _f_ppf(q, d, d2) == f.ppf(q, d, d2)
