"""Tests of rescu.scene.symmetry: cross ratio, translation symmetry, rectifying homography."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from rescu.scene import symmetry as S


def apply(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ h.T
    return q[:, :2] / q[:, 2:]


def random_homography(rng: np.random.Generator) -> np.ndarray:
    h = np.eye(3) + rng.normal(0, 0.3, (3, 3))
    h[2, :2] = rng.normal(0, 0.002, 2)
    h[:2, 2] = rng.uniform(-200, 200, 2)
    return h


def test_cross_ratio_equal_spacing_is_four_thirds():
    pts = np.array([[0.0, 0], [1, 1], [2, 2], [3, 3]])
    assert S.cross_ratio(*pts) == pytest.approx(4 / 3, abs=1e-12)
    # reversed order gives the same value
    assert S.cross_ratio(*pts[::-1]) == pytest.approx(4 / 3, abs=1e-12)
    # 0, 1, 3, 4: AC=3, BD=3, BC=2, AD=4 -> 9/8
    q = np.array([[0.0, 0], [1, 0], [3, 0], [4, 0]])
    assert S.cross_ratio(*q) == pytest.approx(9 / 8, abs=1e-12)


def test_cross_ratio_batched_and_degenerate():
    a = np.zeros((2, 2))
    b = np.array([[1.0, 0], [1, 0]])
    c = np.array([[2.0, 0], [1, 0]])
    d = np.array([[3.0, 0], [3, 0]])
    out = S.cross_ratio(a, b, c, d)
    assert out.shape == (2,) and out[0] == pytest.approx(4 / 3) and np.isnan(out[1])
    with pytest.raises(ValueError, match="same shape"):
        S.cross_ratio(np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(3))


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), spacing=st.lists(st.floats(0.2, 5.0), min_size=3,
                                                          max_size=3))
def test_cross_ratio_invariant_under_random_homographies(seed, spacing):
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(spacing)]) * 40
    p0 = rng.uniform(-100, 100, 2)
    ang = rng.uniform(0, np.pi)
    pts = p0 + t[:, None] * [np.cos(ang), np.sin(ang)]
    h = random_homography(rng)
    w = np.c_[pts, np.ones(4)] @ h[2]
    assume(np.all(w > 0.2) or np.all(w < -0.2))  # no point sent through infinity
    assume(abs(np.linalg.det(h)) > 1e-3)
    cr0 = S.cross_ratio(*pts)
    cr1 = S.cross_ratio(*apply(h, pts))
    assert cr1 == pytest.approx(cr0, rel=1e-7)
    if np.allclose(spacing, spacing[0]):
        assert cr1 == pytest.approx(4 / 3, rel=1e-7)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_equally_spaced_points_under_homography_give_four_thirds(seed):
    rng = np.random.default_rng(seed)
    pts = np.arange(4)[:, None] * rng.uniform(10, 80, 2) + rng.uniform(-50, 50, 2)
    h = random_homography(rng)
    w = np.c_[pts, np.ones(4)] @ h[2]
    assume(np.all(w > 0.2) or np.all(w < -0.2))
    assume(abs(np.linalg.det(h)) > 1e-3)
    assert S.cross_ratio(*apply(h, pts)) == pytest.approx(4 / 3, rel=1e-7)


def test_row_cross_ratios():
    p = np.c_[np.arange(6.0) * 10, np.zeros(6)]
    np.testing.assert_allclose(S.row_cross_ratios(p), np.full(3, 4 / 3))
    assert S.row_cross_ratios(p[:3]).shape == (0,)


def _row_points(xs: np.ndarray, h: np.ndarray, words: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Feature points (words, N, 2) and centres (N, 2) of instances at xs, seen by h."""
    offs = np.array([[0.0, 0], [0.5, 0.2], [0.2, 0.6]])[:words]
    fp = np.stack([apply(h, np.c_[xs + o[0], np.full(len(xs), o[1])]) for o in offs])
    centres = apply(h, np.c_[xs + 0.25, np.full(len(xs), 0.25)])
    return fp, centres


H = np.array([[50.0, 4, 30], [3, 50, 200], [0.06, 0.002, 1]])


def test_translation_symmetry_equal_row_detected():
    fp, c = _row_points(np.arange(6.0), H)
    ts = S.translation_symmetry(fp, c, [np.arange(6)])
    assert ts is not None and ts.detected
    assert ts.cross_ratio == pytest.approx(4 / 3, abs=1e-9)
    assert ts.n_tuples == 3 * 3  # 3 consecutive 4-tuples x 3 words


def test_translation_symmetry_unequal_row_not_detected():
    xs = np.array([0.0, 1.0, 2.5, 3.5, 5.5, 6.5])
    fp, c = _row_points(xs, H)
    ts = S.translation_symmetry(fp, c, [np.arange(6)])
    assert ts is not None and not ts.detected
    assert abs(ts.cross_ratio - 4 / 3) > 0.06


def test_translation_symmetry_frontal_row_with_noise_detected():
    rng = np.random.default_rng(0)
    fp, c = _row_points(np.arange(5.0), np.diag([60.0, 60, 1]))
    fp = fp + rng.normal(0, 0.5, fp.shape)
    ts = S.translation_symmetry(fp, c, [np.arange(5)])
    assert ts.detected and ts.n_tuples == 6


def test_translation_symmetry_needs_four_instances_and_uses_centres_without_features():
    fp, c = _row_points(np.arange(3.0), H)
    assert S.translation_symmetry(fp, c, [np.arange(3)]) is None
    assert S.translation_symmetry(None, c, []) is None
    _, c5 = _row_points(np.arange(5.0), np.diag([60.0, 60, 1]))
    ts = S.translation_symmetry(None, c5, [np.arange(5)])
    assert ts.detected and ts.n_tuples == 2
    # stage-II instances without features: feature_points has fewer columns
    fp5, c5 = _row_points(np.arange(5.0), np.diag([60.0, 60, 1]))
    ts = S.translation_symmetry(fp5[:, :3], c5, [np.arange(5)])
    assert ts.detected and ts.n_tuples == 2  # both 4-tuples fall back to the centres


def test_symmetry_params():
    assert S.SymmetryParams.from_dict({"threshold": 0.1}).threshold == 0.1
    with pytest.raises(ValueError, match="nope"):
        S.SymmetryParams.from_dict({"nope": 1})
    with pytest.raises(ValueError, match="min_instances"):
        S.SymmetryParams(min_instances=3)
    # a stricter threshold rejects what a looser one accepts
    xs = np.array([0.0, 1.0, 2.08, 3.08, 4.16])
    fp, c = _row_points(xs, np.diag([60.0, 60, 1]))
    loose = S.translation_symmetry(fp, c, [np.arange(5)], S.SymmetryParams(threshold=0.06))
    strict = S.translation_symmetry(fp, c, [np.arange(5)], S.SymmetryParams(threshold=0.001))
    assert loose.cross_ratio == strict.cross_ratio
    assert loose.detected and not strict.detected


# ----------------------------------------------------------------------------- rectify
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_rectification_sends_vp_to_infinity_and_rows_parallel(seed):
    rng = np.random.default_rng(seed)
    vp = np.array([*rng.uniform(-3000, 3000, 2), 1.0])
    centre = rng.uniform(0, 640, 2)
    assume(np.linalg.norm(vp[:2] - centre) > 400)
    h = S.vp_rectifying_homography(vp, centre)
    hv = h @ vp
    assert abs(hv[2]) < 1e-12 * np.linalg.norm(hv)
    # centre fixed
    np.testing.assert_allclose(apply(h, centre[None])[0], centre, atol=1e-6)
    # lines through the VP (rows) map to parallel lines, with affine spacing
    dirs = []
    for _ in range(3):
        a = centre + rng.uniform(-150, 150, 2)
        pts = a + np.linspace(0, 0.3, 4)[:, None] * (vp[:2] - a)
        q = apply(h, pts)
        d = q[-1] - q[0]
        dirs.append(d / np.linalg.norm(d))
        # collinear after the map
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        np.testing.assert_allclose((q - q[0]) @ n, 0, atol=1e-6 * np.linalg.norm(d))
    for d in dirs[1:]:
        assert abs(dirs[0][0] * d[1] - dirs[0][1] * d[0]) < 1e-9


def test_rectification_makes_equal_3d_spacing_equal_in_image():
    xs = np.arange(5.0)
    fp, c = _row_points(xs, H)
    vp = H @ [1.0, 0, 0]
    h = S.vp_rectifying_homography(vp, c.mean(axis=0))
    q = apply(h, fp[0])
    gaps = np.linalg.norm(np.diff(q, axis=0), axis=1)
    np.testing.assert_allclose(gaps, gaps[0], rtol=1e-9)
    g0 = np.linalg.norm(np.diff(fp[0], axis=0), axis=1)
    assert g0.max() / g0.min() > 1.2  # it was not equal before


def test_rectification_identity_at_infinity_and_errors():
    np.testing.assert_array_equal(S.vp_rectifying_homography(np.array([1.0, 0, 0]),
                                                             [10.0, 10.0]), np.eye(3))
    with pytest.raises(ValueError, match="centre"):
        S.vp_rectifying_homography(np.array([10.0, 10.0, 1.0]), [10.0, 10.0])
    with pytest.raises(ValueError, match="vp"):
        S.vp_rectifying_homography(np.zeros(2), [1.0, 1.0])


def test_straddling_tuples_are_not_translation_symmetry():
    # spacings 1, 1, 2, 1: the two 4-tuples have cr 1.5 and 1.125; their plain median
    # (1.3125) is within 0.06 of 4/3, but neither tuple is
    xs = np.array([0.0, 1.0, 2.0, 4.0, 5.0])
    fp, c = _row_points(xs, np.diag([60.0, 60, 1]))
    np.testing.assert_allclose(S.row_cross_ratios(fp[0]), [1.5, 1.125])
    ts = S.translation_symmetry(fp, c, [np.arange(5)])
    assert not ts.detected and ts.cross_ratio == pytest.approx(1.125)  # upper median dev.
