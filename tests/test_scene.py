"""Tests of rescu.scene.analyse: analyse_scene, SceneParams, rectify_pattern."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from rescu.scene import analyse as SC
from rescu.scene.vp.errors import vector_error
from rescu.types import ImageResult, Instance, Pattern, VanishingPoint

WORDS = np.array([[0, 0], [0.6, 0], [0.6, 0.6], [0, 0.6], [0.3, 0.3], [0.18, 0.42]])
H_PERSP = np.array([[60.0, 5, 100], [2, 60, 150], [0.08, 0.005, 1.0]])
H_FRONTAL = np.array([[60.0, 0, 100], [0, 60, 150], [0, 0, 1.0]])


def project(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ h.T
    return q[:, :2] / q[:, 2:]


def make_pattern(h: np.ndarray, xs: np.ndarray, ny: int = 1, pid: int = 0,
                 noise: float = 0.0, seed: int = 0, score: float = 0.5,
                 with_features: bool = True) -> Pattern:
    rng = np.random.default_rng(seed)
    inst, fps = [], []
    for j in range(ny):
        for x in xs:
            ph = project(h, WORDS + [x, j]) + rng.normal(0, noise, (len(WORDS), 2))
            q = ph[:4]
            inst.append(Instance((q[:, 0].min(), q[:, 1].min(), np.ptp(q[:, 0]),
                                  np.ptp(q[:, 1]))))
            fps.append(ph)
    fp = np.transpose(np.array(fps), (1, 0, 2)) if with_features else None
    return Pattern(id=pid, score=score, instances=inst, feature_points=fp)


def result(*patterns: Pattern) -> ImageResult:
    return ImageResult(image="images/x.png", width=640, height=480, method="rescu-i",
                       patterns=list(patterns))


def test_params_nested_from_dict():
    p = SC.SceneParams.from_dict({"vp": {"ransac_iterations": 10, "seed": 3},
                                  "symmetry": {"threshold": 0.05}, "rectify_max_side": 256})
    assert p.vp.ransac_iterations == 10 and p.vp.seed == 3
    assert p.symmetry.threshold == 0.05 and p.rectify_max_side == 256
    assert SC.SceneParams.from_dict({}) == SC.SceneParams()
    with pytest.raises(ValueError, match="extra_key"):
        SC.SceneParams.from_dict({"extra_key": 1})
    with pytest.raises(ValueError, match="bad_vp_key"):
        SC.SceneParams.from_dict({"vp": {"bad_vp_key": 1}})
    with pytest.raises(ValueError, match="symmetry"):
        SC.SceneParams.from_dict({"symmetry": 3})


def test_empty_result_has_no_vp():
    r = result()
    out = SC.analyse_scene(r)
    assert out.patterns == [] and out.vanishing_point is None
    assert out.dominant_pattern is None and out.method == "rescu-i"


def test_frontal_row_of_five_vp_at_infinity_and_ts():
    r = result(make_pattern(H_FRONTAL, np.arange(5.0), noise=0.3, seed=1))
    out = SC.analyse_scene(r)
    p = out.patterns[0]
    assert p.count == 5 and out.dominant_pattern == 0
    assert p.vanishing_point is not None and p.vanishing_point.homogeneous[2] == 0.0
    assert not p.vanishing_point.inside_image
    assert p.translation_symmetry is not None and p.translation_symmetry.detected
    assert p.translation_symmetry.n_tuples == 2 * len(WORDS)
    assert p.extra["rows"] == [[0, 1, 2, 3, 4]] or p.extra["rows"] == [[4, 3, 2, 1, 0]]
    np.testing.assert_array_equal(out.vanishing_point.homogeneous,
                                  p.vanishing_point.homogeneous)


def test_unequal_row_ts_not_detected():
    r = result(make_pattern(H_PERSP, np.array([0.0, 1.0, 2.6, 3.6, 5.4, 6.4])))
    p = SC.analyse_scene(r).patterns[0]
    assert p.translation_symmetry is not None and not p.translation_symmetry.detected


def test_perspective_grid_vp_rows_towards_vp_and_input_unchanged():
    pat = make_pattern(H_PERSP, np.arange(6.0), ny=3, noise=0.5)
    r = result(pat)
    before = json.dumps(r.to_json(), sort_keys=True)
    out = SC.analyse_scene(r)
    assert json.dumps(r.to_json(), sort_keys=True) == before
    p = out.patterns[0]
    gt = H_PERSP @ [1.0, 0, 0]
    assert vector_error(p.vanishing_point.homogeneous, gt, (640, 480)) < 1.0
    assert p.translation_symmetry.detected
    assert sorted(sorted(r_) for r_ in p.extra["rows"]) == [list(range(6 * j, 6 * j + 6))
                                                            for j in range(3)]
    # VP at x > 0: each row ordered left to right (towards the VP)
    for row in p.extra["rows"]:
        assert row == sorted(row)
    # JSON round trip keeps the scene fields
    back = ImageResult.from_json(json.loads(json.dumps(out.to_json())))
    np.testing.assert_allclose(back.vanishing_point.homogeneous,
                               out.vanishing_point.homogeneous, atol=1e-8)
    assert back.patterns[0].translation_symmetry.detected


def test_dominant_and_image_vp_rules():
    small = make_pattern(H_PERSP, np.arange(4.0), pid=0, score=0.9)
    big = make_pattern(H_FRONTAL, np.arange(6.0), pid=7, score=0.1)
    out = SC.analyse_scene(result(small, big))
    assert out.dominant_pattern == 7
    assert out.vanishing_point.homogeneous[2] == 0.0  # the dominant (frontal) one
    # dominant pattern without a VP (scattered): fall back to the other pattern's VP
    scattered = Pattern(id=3, score=0.9, instances=[
        Instance((0.0, 0, 10, 10)), Instance((100.0, 37, 10, 10)), Instance((31.0, 200, 10, 10)),
        Instance((300.0, 90, 10, 10)), Instance((170.0, 400, 10, 10)),
        Instance((500.0, 10, 10, 10)), Instance((420.0, 300, 10, 10))])
    out = SC.analyse_scene(result(small, scattered))
    assert out.dominant_pattern == 3
    assert out.patterns[1].vanishing_point is None
    assert out.patterns[1].translation_symmetry is None
    np.testing.assert_array_equal(out.vanishing_point.homogeneous,
                                  out.patterns[0].vanishing_point.homogeneous)


def test_stage2_instances_without_features():
    pat = make_pattern(H_FRONTAL, np.arange(6.0), noise=0.2)
    pat.feature_points = pat.feature_points[:, :4]  # last two added by stage II
    out = SC.analyse_scene(result(pat))
    assert out.patterns[0].count == 6 and out.patterns[0].translation_symmetry.detected
    bad = copy.deepcopy(pat)
    bad.feature_points = np.zeros((2, 9, 2))
    with pytest.raises(ValueError, match="feature_points"):
        SC.analyse_scene(result(bad))


def test_deterministic():
    r = result(make_pattern(H_PERSP, np.arange(7.0), ny=4, noise=1.0))
    p = SC.SceneParams.from_dict({"vp": {"ransac_iterations": 30, "seed": 5}})
    a, b = SC.analyse_scene(r, p), SC.analyse_scene(r, p)
    assert json.dumps(a.to_json(), sort_keys=True) == json.dumps(b.to_json(), sort_keys=True)


# ----------------------------------------------------------------------------- rectify
def _image() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)


def test_rectify_crop_when_vp_at_infinity_or_missing():
    rgb = _image()
    pat = Pattern(id=0, score=1.0, instances=[Instance((40.0, 40, 20, 20)),
                                              Instance((80.0, 40, 20, 20))])
    p = SC.SceneParams(rectify_padding=0.0)
    crop = SC.rectify_pattern(rgb, 1.0, pat, p)
    np.testing.assert_array_equal(crop, rgb[40:60, 40:100])
    pat.vanishing_point = VanishingPoint(np.array([1.0, 0, 0]), False, 2)
    np.testing.assert_array_equal(SC.rectify_pattern(rgb, 1.0, pat, p), rgb[40:60, 40:100])
    # original pixels -> processed (half size)
    half = rgb[::2, ::2].copy()
    out = SC.rectify_pattern(half, 0.5, pat, p)
    np.testing.assert_array_equal(out, half[20:30, 20:50])
    assert SC.rectify_pattern(rgb, 1.0, Pattern(0, 1.0, []), p) is None


def test_rectify_perspective_bounded_and_ill_posed():
    rgb = _image()
    pat = Pattern(id=0, score=1.0, instances=[Instance((40.0 + 30 * k, 100, 20, 20))
                                              for k in range(4)])
    pat.vanishing_point = VanishingPoint(np.array([600.0, 110, 1]) / np.linalg.norm(
        [600.0, 110, 1]), False, 4)
    out = SC.rectify_pattern(rgb, 1.0, pat, SC.SceneParams(rectify_max_side=64))
    assert out is not None and out.dtype == np.uint8 and out.ndim == 3
    assert max(out.shape[:2]) <= 64
    # VP inside the region: no view
    pat.vanishing_point = VanishingPoint(np.array([90.0, 110, 1]) / np.linalg.norm(
        [90.0, 110, 1]), True, 4)
    assert SC.rectify_pattern(rgb, 1.0, pat) is None


def test_rectify_equalises_rendered_spacing():
    """Render a perspective row of bright bars; after rectification the gaps are equal."""
    import cv2

    flat = np.zeros((100, 700, 3), np.uint8)
    for k in range(6):
        flat[20:80, 50 + 100 * k: 90 + 100 * k] = 255
    h = np.array([[0.6, 0.0, 20], [0.05, 0.6, 60], [0.0012, 0.0, 1.0]])
    img = cv2.warpPerspective(flat, h, (640, 300))
    inst = []
    for k in range(6):
        q = project(h, np.array([[50 + 100 * k, 20], [90 + 100 * k, 20],
                                 [90 + 100 * k, 80], [50 + 100 * k, 80.0]]))
        inst.append(Instance((q[:, 0].min(), q[:, 1].min(), np.ptp(q[:, 0]), np.ptp(q[:, 1]))))
    v = h @ [1.0, 0, 0]
    pat = Pattern(0, 1.0, inst, vanishing_point=VanishingPoint(v / np.linalg.norm(v), False, 6))
    out = SC.rectify_pattern(img, 1.0, pat, SC.SceneParams(rectify_padding=0.05))
    assert out is not None
    gray = out.mean(axis=2)
    col = gray.max(axis=0) > 128  # bar columns
    # bar starts from the middle row band
    rows_lit = gray[:, col].mean(axis=1) > 60
    band = gray[np.nonzero(rows_lit)[0][len(np.nonzero(rows_lit)[0]) // 2]] > 128
    starts = np.nonzero(band[1:] & ~band[:-1])[0]
    assert len(starts) == 6
    gaps = np.diff(starts)
    assert gaps.max() - gaps.min() <= 3  # equal to the pixel
    before = [i.bbox[0] for i in inst]
    assert np.ptp(np.diff(before)) > 10  # unequal before


def test_image_vp_joins_patterns_that_share_the_dominant_vp():
    # two RPs on one plane, rows along the plane's X axis (same VP), and a third RP on
    # a plane turned by 90 degrees (rows along another direction)
    a = make_pattern(H_PERSP, np.arange(6.0), pid=0, noise=0.5, seed=1)
    b = make_pattern(H_PERSP @ np.array([[1, 0, 0], [0, 1, 3.0], [0, 0, 1]]),
                     np.arange(5.0) * 1.3, pid=1, noise=0.5, seed=2)
    c = make_pattern(H_PERSP @ np.array([[0, 1, 8.0], [1, 0, 0], [0, 0, 1]]),
                     np.arange(4.0), pid=2, noise=0.5, seed=3)
    out = SC.analyse_scene(result(a, b, c))
    assert out.dominant_pattern == 0
    own = out.patterns[0].vanishing_point
    assert out.vanishing_point.support == own.support + out.patterns[1].vanishing_point.support
    gt = H_PERSP @ np.array([1.0, 0, 0])
    assert vector_error(out.vanishing_point.homogeneous, gt, (640, 480)) < 0.5
    # joint estimation off: the dominant pattern's own VP
    p = SC.SceneParams.from_dict({"vp": {"joint_alpha": 0}})
    out = SC.analyse_scene(result(a, b, c), p)
    np.testing.assert_array_equal(out.vanishing_point.homogeneous,
                                  out.patterns[0].vanishing_point.homogeneous)


def test_image_vp_from_the_rows_of_patterns_too_small_for_a_vp_of_their_own():
    # two RPs on one plane, each one row followed by two visual words: 2 implicit lines
    # each, fewer than vp.min_lines = 3, so neither has a VP of its own
    a = make_pattern(H_PERSP, np.arange(5.0), pid=0, noise=0.3, seed=1)
    b = make_pattern(H_PERSP @ np.array([[1, 0, 0], [0, 1, 3.0], [0, 0, 1]]),
                     np.arange(4.0), pid=1, noise=0.3, seed=2)
    a.feature_points, b.feature_points = a.feature_points[[0, 4]], b.feature_points[[1, 5]]
    out = SC.analyse_scene(result(a, b))
    assert all(p.vanishing_point is None for p in out.patterns)
    assert out.vanishing_point is not None and out.vanishing_point.support == 4
    gt = H_PERSP @ np.array([1.0, 0, 0])
    assert vector_error(out.vanishing_point.homogeneous, gt, (640, 480)) < 1.0  # degrees
    # union_rows off: only patterns with a VP of their own give the image VP
    p = SC.SceneParams.from_dict({"vp": {"union_rows": False}})
    assert SC.analyse_scene(result(a, b), p).vanishing_point is None


def test_rps_set_aside_as_one_structure_give_the_image_vp_only_when_the_reported_do_not():
    """A reported RP of scattered instances has no VP; the rows of an RP that RESCU-I set
    aside as one structure (kept in ``candidate_patterns``) still point to one, which
    becomes the RP-based image VP. The set-aside RP is not reported, and when a reported
    RP has a VP of its own, it is the image VP."""
    scattered = Pattern(id=0, score=0.9, instances=[
        Instance((0.0, 0, 10, 10)), Instance((100.0, 37, 10, 10)), Instance((31.0, 200, 10, 10)),
        Instance((300.0, 90, 10, 10)), Instance((170.0, 400, 10, 10))])
    ledge = make_pattern(H_PERSP, np.arange(6.0), ny=2, noise=0.3)
    aside = dict(ledge.to_json(), dropped="one structure")
    r = result(scattered)
    assert SC.analyse_scene(r).vanishing_point is None
    r.extra["candidate_patterns"] = [aside, dict(aside, dropped="low confidence")]
    # the hidden RPs' rows off: the set-aside structure alone gives the VP
    out = SC.analyse_scene(r, SC.SceneParams.from_dict({"vp": {"hidden_rows": False}}))
    assert [p.id for p in out.patterns] == [0] and out.dominant_pattern == 0
    assert vector_error(out.vanishing_point.homogeneous, H_PERSP @ [1.0, 0, 0],
                        (640, 480)) < 1.0
    frontal = make_pattern(H_FRONTAL, np.arange(6.0), pid=1)
    r = result(frontal)
    r.extra["candidate_patterns"] = [aside]
    assert SC.analyse_scene(r).vanishing_point.homogeneous[2] == 0.0


def test_the_rows_of_stage_one_rps_hidden_for_low_confidence_give_the_image_vp():
    """Stage-I RPs that the confidence hid (``candidate_patterns``, ``"low confidence"``)
    still have rows towards a VP: they give the RP-based image VP, also on an image with
    no reported RP, and stay unreported. Not the dense source's hidden RPs, not with
    ``vp.hidden_rows: false``."""
    scattered = Pattern(id=0, score=0.9, instances=[
        Instance((0.0, 0, 10, 10)), Instance((100.0, 37, 10, 10)), Instance((31.0, 200, 10, 10)),
        Instance((300.0, 90, 10, 10)), Instance((170.0, 400, 10, 10))])
    slivers = make_pattern(H_PERSP, np.arange(6.0), ny=2, noise=0.3)
    hidden = dict(slivers.to_json(), dropped="low confidence", source="stage1")
    r = result(scattered)
    r.extra["candidate_patterns"] = [hidden]
    out = SC.analyse_scene(r)
    assert [p.id for p in out.patterns] == [0] and out.dominant_pattern == 0
    assert out.patterns[0].vanishing_point is None
    assert vector_error(out.vanishing_point.homogeneous, H_PERSP @ [1.0, 0, 0],
                        (640, 480)) < 1.0
    assert out.extra["candidate_patterns"] == [hidden]
    # the reported RPs' own image VP (none here), for the joint estimator
    assert out.extra["reported_rp_vanishing_point"] is None
    # recomputed from the analysed result (the studies' entry point): the same VP
    np.testing.assert_array_equal(SC.image_rp_vp(out).homogeneous,
                                  out.vanishing_point.homogeneous)
    off = SC.SceneParams.from_dict({"vp": {"hidden_rows": False}})
    assert SC.analyse_scene(r, off).vanishing_point is None
    r.extra["candidate_patterns"] = [dict(hidden, source="dense")]
    assert SC.analyse_scene(r).vanishing_point is None
    alone = result()
    alone.extra["candidate_patterns"] = [hidden]
    out = SC.analyse_scene(alone)
    assert out.patterns == [] and out.dominant_pattern is None
    assert vector_error(out.vanishing_point.homogeneous, H_PERSP @ [1.0, 0, 0],
                        (640, 480)) < 1.0
    assert SC.analyse_scene(alone, off).vanishing_point is None


def test_a_vp_switch_that_is_not_true_or_false_is_refused():
    with pytest.raises(ValueError, match=r"hidden_rows \(configuration key "
                       r"scene\.vp\.hidden_rows\) = .maybe.: .* not of type .boolean."):
        SC.SceneParams.from_dict({"vp": {"hidden_rows": "maybe"}})
    with pytest.raises(ValueError, match="union_rows"):
        SC.SceneParams.from_dict({"vp": {"union_rows": 1}})
