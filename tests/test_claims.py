"""Claims with support (rescu.scene.claims) and captions / summary lines that state only
those claims (rescu.captions.caption): one test per claim type."""

from __future__ import annotations

import numpy as np
import pytest

from rescu.captions import caption as C
from rescu.scene import claims as CL
from rescu.types import ImageResult, Instance, Pattern, TranslationSymmetry, VanishingPoint

RGB = np.zeros((40, 60, 3), np.uint8)


def _project(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


def grid_pattern(H: np.ndarray, n_rows: int = 3, n_cols: int = 5, noise: float = 0.0,
                 seed: int = 0) -> Pattern:
    """A grid of 20 x 20 objects 40 apart on a plane seen through ``H``; each object has
    four features (its corners, 4 visual words); rows along x, one row per grid row."""
    rng = np.random.default_rng(seed)
    inst, fp, rows = [], [], []
    for r in range(n_rows):
        row = []
        for c in range(n_cols):
            corners = np.array([[40 * c, 40 * r], [40 * c + 20, 40 * r],
                                [40 * c, 40 * r + 20], [40 * c + 20, 40 * r + 20]], float)
            p = _project(H, corners) + rng.normal(0, noise, (4, 2))
            x0, y0 = p.min(axis=0)
            x1, y1 = p.max(axis=0)
            row.append(len(inst))
            inst.append(Instance((x0, y0, x1 - x0, y1 - y0)))
            fp.append(p)
        rows.append(row)
    pat = Pattern(0, 0.9, inst, feature_points=np.transpose(np.array(fp), (1, 0, 2)))
    pat.extra["rows"] = rows
    return pat


FRONTAL = np.array([[1.0, 0, 100], [0, 1.0, 100], [0, 0, 1]])
PROJECTIVE = np.array([[1.0, 0, 100], [0, 1.0, 100], [0.0025, 0, 1]])  # rows converge


def image_result(*patterns: Pattern, **extra) -> ImageResult:
    return ImageResult("images/x.png", 640, 480, "rescu-ii", list(patterns),
                       dominant_pattern=0 if patterns else None, extra=dict(extra))


def with_vp(p: Pattern, xyw: tuple[float, float, float]) -> Pattern:
    p.vanishing_point = VanishingPoint(np.asarray(xyw, float) / np.linalg.norm(xyw),
                                       False, 12)
    return p


# ----------------------------------------------------------------------------- an RP's VP
def test_frontal_grid_vp_is_not_claimed() -> None:
    # the estimator's answer on parallel rows: some far point; the claim test says frontal
    p = with_vp(grid_pattern(FRONTAL, noise=0.3), (1e5, 150.0, 1.0))
    status, ev = CL.pattern_vp_evidence(p)
    assert status == "frontal" and ev["rows"] == 3 and ev["p_parallel"] > 0.001
    res = CL.supported_claims(image_result(p))
    assert res.patterns[0].vanishing_point is None
    assert res.patterns[0].extra["vp_status"] == "frontal"
    assert res.extra["vp_status"] == "none"
    cap = C.caption_result(RGB, res, "x.png", C.TemplateCaptioner())["enhanced"]
    assert "vanishing point" not in cap and "VP" not in C.summary_line(res)


def test_projective_grid_vp_is_claimed_and_said_in_caption_and_summary() -> None:
    p = grid_pattern(PROJECTIVE, noise=0.3)
    vp = PROJECTIVE @ np.array([1.0, 0, 0])  # the image of the rows' point at infinity
    p = with_vp(p, tuple(vp))
    status, ev = CL.pattern_vp_evidence(p)
    assert status == "supported", ev
    assert ev["residual_deg"] < 1.0 and ev["p_parallel"] < 1e-3
    res = CL.supported_claims(image_result(p))
    assert res.patterns[0].vanishing_point is not None
    cap = C.caption_result(RGB, res, "x.png", C.TemplateCaptioner())["enhanced"]
    assert "form a vanishing point outside of the image" in cap
    assert "VP outside the image" in C.summary_line(res)


def test_vp_off_the_lines_is_inconsistent_and_one_short_row_too_few() -> None:
    p = with_vp(grid_pattern(PROJECTIVE, noise=0.3), (400.0, 900.0, 1.0))  # far below
    assert CL.pattern_vp_evidence(p)[0] == "inconsistent"
    short = with_vp(grid_pattern(PROJECTIVE, n_rows=1, n_cols=2), (500.0, 100.0, 1.0))
    assert CL.pattern_vp_evidence(short)[0] == "too_few_rows"
    # one row: its feature tracks (top and bottom corners) must converge at the VP
    vp = tuple(PROJECTIVE @ np.array([1.0, 0, 0]))
    one_row = with_vp(grid_pattern(PROJECTIVE, n_rows=1, n_cols=5, noise=0.3), vp)
    status, ev = CL.pattern_vp_evidence(one_row)
    assert status == "supported" and ev["tracks"] == 5, ev
    flat_row = with_vp(grid_pattern(FRONTAL, n_rows=1, n_cols=5, noise=0.3), (1e5, 110, 1))
    assert CL.pattern_vp_evidence(flat_row)[0] == "frontal"
    no_tracks = with_vp(grid_pattern(PROJECTIVE, n_rows=1, n_cols=5), vp)
    no_tracks.feature_points = None
    assert CL.pattern_vp_evidence(no_tracks)[0] == "too_few_rows"
    at_inf = with_vp(grid_pattern(PROJECTIVE, noise=0.3), (1.0, 0.0, 0.0))
    assert CL.pattern_vp_evidence(at_inf)[0] == "frontal"


# ----------------------------------------------------------------------------- image VPs
def test_image_vps_need_more_lines_than_chance_and_frontal_ones_are_at_infinity() -> None:
    lines = {"lines": 400, "rp_rows": 0, "weight": 5000.0, "inlier_angle_deg": 2.0}
    far = {"homogeneous": [1.0, 0.3, 1e-9], "inside_image": False, "support": 80,
           "cues": {"lines": 80, "rp_rows": 0}, "direction": [0.9, 0.27, 0.01]}
    weak = {"homogeneous": [320.0, 240.0, 1.0], "inside_image": True, "support": 3,
            "cues": {"lines": 3, "rp_rows": 0}}
    good = {"homogeneous": [900.0, 250.0, 1.0], "inside_image": False, "support": 60,
            "cues": {"lines": 60, "rp_rows": 0}}
    # a frontal view: its VP is reported at infinity (w = 0), along its image direction
    res = CL.supported_claims(image_result(vanishing_points=[far, weak], vp_lines=lines))
    assert res.extra["vp_status"] == "frontal"
    [v] = res.extra["vanishing_points"]
    assert v["status"] == "at_infinity" and v["homogeneous"][2] == 0.0 and v["nfa"] < 1e-30
    assert np.allclose(v["homogeneous"][:2], np.array([1.0, 0.3]) / np.hypot(1.0, 0.3))
    assert v["direction"][2] == 0.0
    assert res.vanishing_point is not None and res.vanishing_point.homogeneous[2] == 0.0
    [r] = res.extra["rejected_vanishing_points"]
    assert r["status"] == "weak" and r["support"] == 3
    # a finite VP comes first, the one at infinity after it
    ok = CL.supported_claims(image_result(vanishing_points=[far, good], vp_lines=lines))
    assert ok.extra["vp_status"] == "supported"
    assert [v["homogeneous"][2] for v in ok.extra["vanishing_points"]] == [1.0, 0.0]
    assert ok.vanishing_point is not None and ok.vanishing_point.homogeneous[0] == 900.0
    # a VP that gathers a few of many lines (fur, letters, the rims of cells) is chance:
    # about 9 of 400 lines of random directions pass within 2 degrees of any point
    few = dict(good, support=20, cues={"lines": 20, "rp_rows": 0})
    chance = CL.supported_claims(image_result(vanishing_points=[few], vp_lines=lines))
    assert chance.vanishing_point is None and chance.extra["vp_status"] == "weak"
    assert chance.extra["rejected_vanishing_points"][0]["nfa"] > 1.0
    many = dict(good, support=60, cues={"lines": 60, "rp_rows": 0})
    assert CL.supported_claims(image_result(vanishing_points=[many], vp_lines=lines)
                               ).extra["vp_status"] == "supported"
    # RP rows count only when an RP's own VP passed its test
    rows_vp = {"homogeneous": [3412.0, 263.0, 1.0], "inside_image": False, "support": 77,
               "weight": 13144.0, "cues": {"lines": 14, "rp_rows": 63}}
    joint = {"lines": 135, "rp_rows": 118, "weight": 32131.0}
    frontal_rows = with_vp(grid_pattern(FRONTAL, noise=0.3), (1e5, 150.0, 1.0))
    res = CL.supported_claims(image_result(frontal_rows, vanishing_points=[rows_vp],
                                           vp_lines=joint))
    assert res.vanishing_point is None and res.extra["vp_status"] == "weak"
    proj = grid_pattern(PROJECTIVE, noise=0.3)
    proj = with_vp(proj, tuple(PROJECTIVE @ np.array([1.0, 0, 0])))
    res = CL.supported_claims(image_result(proj, vanishing_points=[rows_vp], vp_lines=joint))
    assert res.extra["vp_status"] == "supported"
    assert CL.convergence_deg([1.0, 0.0, 0.0], (640, 480)) == 0.0
    assert CL.convergence_deg([320.0, 240.0, 1.0], (640, 480)) == pytest.approx(180.0)


def test_line_nfa_is_the_expected_number_of_chance_points() -> None:
    # 2 degrees: a random line passes with p = 1/45; n (n - 1) (n - 2) / 2 frames tried
    assert CL.line_nfa(1, 3, 2.0) == pytest.approx(3.0 * (1.0 - (44 / 45) ** 3))
    assert CL.line_nfa(0, 100, 2.0) == 100 * 99 * 98 / 2      # every frame tried
    assert CL.line_nfa(5, 4, 2.0) == 0.0                       # more inliers than lines
    assert CL.line_nfa(30, 400, 2.0) < CL.line_nfa(20, 400, 2.0) < CL.line_nfa(20, 800, 2.0)
    assert CL.line_nfa(20, 400, 1.0) < CL.line_nfa(20, 400, 2.0)


# ----------------------------------------------------------------------------- TS, layout
def test_ts_status_and_caption_agree() -> None:
    p = grid_pattern(FRONTAL)
    assert CL.ts_status(p) == "too_few_instances"
    p.translation_symmetry = TranslationSymmetry(True, 1.34, 6)
    res = CL.supported_claims(image_result(p))
    assert res.patterns[0].extra["ts_status"] == "equal_spacing"
    cap = C.caption_result(RGB, res, "x.png", C.TemplateCaptioner())["enhanced"]
    assert "translation symmetry" in cap and "translation symmetry" in C.summary_line(res)
    p.translation_symmetry = TranslationSymmetry(False, 1.9, 6)
    res = CL.supported_claims(image_result(p))
    assert res.patterns[0].extra["ts_status"] == "unequal_spacing"
    assert "symmetry" not in C.caption_result(RGB, res, "x.png", C.TemplateCaptioner())[
        "enhanced"] + C.summary_line(res)


def test_grid_only_with_rows_and_columns() -> None:
    grid = grid_pattern(FRONTAL)
    assert C.infer_layout(grid) == "grid"
    rng = np.random.default_rng(3)  # 20 boxes scattered over a page
    xy = rng.uniform(0, 600, (20, 2))
    scattered = Pattern(0, 0.5, [Instance((x, y, 14, 9)) for x, y in xy])
    assert C.infer_layout(scattered) == "group"
    cap = C.TemplateCaptioner().caption(RGB, image_result(scattered), "x.png")
    assert cap == "A group of similar objects."
    assert "grid" not in C.summary_line(image_result(scattered))
    assert "; grid" in C.summary_line(image_result(grid))


# ----------------------------------------------------------------------------- nothing found
def test_no_pattern_caption_and_summary() -> None:
    empty = image_result(candidate_patterns=[{"id": 0, "confidence": 0.1}])
    out = C.caption_result(RGB, empty, "x.png", C.TemplateCaptioner())
    assert out == {"base": "No recurring pattern found.",
                   "enhanced": "No recurring pattern found."}
    assert C.summary_line(empty) == "No recurring pattern found."

    class Fixed:
        def caption(self, rgb, result, name):
            return "A cat on a sofa."

    out = C.caption_result(RGB, empty, "x.png", Fixed())
    assert out["base"] == out["enhanced"] == "A cat on a sofa. No recurring pattern found."


def test_summary_shows_confidence_else_score() -> None:
    a, b = grid_pattern(FRONTAL), grid_pattern(FRONTAL)
    b.id, b.extra["confidence"] = 1, 0.834
    line = C.summary_line(image_result(a, b))
    assert line.startswith("2 RPs: 15 (score 0.90), 15 (confidence 0.83)")
