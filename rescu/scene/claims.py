"""Claims with support: which vanishing points and symmetries a result may state.

The estimators of the scene step always return their best answer: a VP from three
nearly parallel feature tracks, or from a third Manhattan direction that a frontal scan
of coins does not have. :func:`supported_claims` (the caption step, before the caption
is written) keeps a claim only when its evidence passes a test, and otherwise says in
the JSON which test failed:

* **An RP's vanishing point** needs at least ``min_rows`` rows of at least
  ``min_row_instances`` instances, each one line (through its instance centres, along
  the mean direction of that centre line and of the feature tracks of each visual word
  along the row), that are *not parallel within noise*: their directions differ by more
  than a chi-square test at level ``parallel_alpha`` allows for points of noise
  ``point_noise`` x the median instance side, and by at least ``min_convergence_deg``;
  and the rows must meet at the VP (no row further than ``max_residual_deg`` from the
  ray from its middle to the VP). Pattern keys: ``vp_status`` (``"supported"``,
  ``"frontal"``: rows parallel or the VP at infinity, ``"too_few_rows"``,
  ``"inconsistent"``: the rows do not meet at the VP, ``"none"``: no VP was estimated)
  and ``vp_evidence`` (the measured numbers). An RP with fewer rows is tested on its
  longest row's own lines instead (its centre line and feature tracks, at least three):
  the same tests, each line meeting the VP (a row in perspective: its top and bottom
  features converge; a frontal one: parallel).
* **The image's vanishing points** (``vanishing_points`` of the joint estimator) each
  need line evidence that chance does not explain, an a-contrario test (Desolneux, Moisan
  and Morel; the test LSD itself and Almansa et al.'s VP detector, PAMI 2003, use): of
  the ``n`` lines the estimator was given (``vp_lines``), ``k`` pass within the inlier
  angle ``a`` of the VP (``vp_lines.inlier_angle_deg``); were the lines' directions
  independent and uniform, each would do so with probability ``p = 2a / 180``, and the
  number of false alarms ``NFA = n (n - 1) (n - 2) / 2 x P[Binomial(n, p) >= k]`` (the
  estimator proposes a frame from each triplet of lines: two for the first VP, a third
  for the second) must be at most ``max_image_nfa``; and ``k`` at least
  ``min_image_support``. Where no RP's own VP passed its test, the RP rows are no
  evidence of convergence (a frontal grid's rows meet anywhere far away) and only the
  VP's LSD segments count (``k`` and ``n`` of segments alone). A VP that gathers a few of
  many lines in every direction (fur, letters, the rims of cells) then fails; one of a
  hundred lines of a street passes. A VP that passes is *at infinity* when the image
  diagonal subtends less than ``min_image_convergence_deg`` at it (lines across the
  image converge less than that: parallel in the picture, a frontal view): it is reported
  as a point at infinity (``w = 0``, ``status`` ``"at_infinity"``), after the finite ones.
  Those that fail move to ``rejected_vanishing_points`` with ``status`` ``"weak"`` and
  their ``nfa``; ``vanishing_point`` is the first reported one (a finite one first), or
  null. The image's ``vp_status``: ``"supported"`` (a finite VP), ``"frontal"`` (only
  VPs at infinity), ``"weak"`` (no VP passed), ``"none"`` (no VP from any cue). Without
  the joint list (fewer than three lines) the RP-only VP is kept when an RP's VP is
  supported.
* **Translation symmetry** is already a test (the cross ratio of rows of at least
  ``scene.symmetry.min_instances`` instances within ``t`` of 4/3); each pattern gets
  ``ts_status``: ``"equal_spacing"``, ``"unequal_spacing"`` or ``"too_few_instances"``.

The VPD tables read the estimators' own folders (``scene/``, ``scene-joint/``), so this
gate changes what a user is told, not the measured VP accuracy.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..params import checked_mapping, config_section
from ..types import ImageResult, Pattern, VanishingPoint
from .vp.geometry import _chi2_sf


@dataclass(frozen=True)
@config_section("scene", "claims")
class ClaimParams:
    """Tests a claim must pass (config section ``scene.claims``; module docstring).

    Attributes
    ----------
    min_row_instances : int
        A line counts when it passes through at least this many instances of one row.
    min_rows : int
        Fewest rows (one line each) for an RP's VP.
    point_noise : float
        Noise floor of a line point, as a fraction of the median instance side.
    parallel_alpha : float
        Level of the chi-square test "the lines are parallel", (0, 1).
    min_convergence_deg : float
        Smallest spread of the line directions for a VP, degrees.
    max_residual_deg : float
        Largest angle between a row and the ray from its middle to the VP, degrees.
    min_image_support : int
        Fewest inlier lines of one of the image's VPs.
    max_image_nfa : float
        Largest number of false alarms of one of the image's VPs (its line support
        against uniform line directions; module docstring), > 0.
    min_image_convergence_deg : float
        Smallest angle the image diagonal subtends at one of the image's VPs, degrees.
    """

    min_row_instances: int
    min_rows: int
    point_noise: float
    parallel_alpha: float
    min_convergence_deg: float
    max_residual_deg: float
    min_image_support: int
    max_image_nfa: float
    min_image_convergence_deg: float

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "ClaimParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        return cls(**checked_mapping(cls, d, "claims parameter"))


# ----------------------------------------------------------------------------- lines
def _fit_line(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Total-least-squares line through ``pts`` (K, 2): (middle (2,), unit direction (2,),
    rms perpendicular residual (pixels, K - 2 degrees of freedom), spread along it
    (sqrt of the sum of squared along-line offsets, pixels))."""
    mid = pts.mean(axis=0)
    q = pts - mid
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    d = vt[0]
    resid = float(np.sqrt(s[1] ** 2 / max(len(pts) - 2, 1))) if len(s) > 1 else 0.0
    return mid, d, resid, float(s[0])


def pattern_lines(pattern: Pattern, min_row_instances: int = 3) -> list[np.ndarray]:
    """The point sets of an RP's row lines, original pixels: per row of
    ``pattern.extra["rows"]`` with at least ``min_row_instances`` instances, the row's
    instance centres and, per visual word, its feature points in that row when it is
    found in at least ``min_row_instances`` of them. Returns a list of (K, 2) arrays."""
    rows = [list(map(int, r)) for r in (pattern.extra.get("rows") or [])]
    boxes = np.array([i.bbox for i in pattern.instances], float).reshape(-1, 4)
    centres = boxes[:, :2] + boxes[:, 2:] / 2.0
    fp = None if pattern.feature_points is None else np.asarray(pattern.feature_points, float)
    out = []
    for r in rows:
        r = [i for i in r if 0 <= i < len(centres)]
        if len(r) < min_row_instances:
            continue
        out.append(centres[r])
        if fp is None or fp.ndim != 3:
            continue
        cols = [i for i in r if i < fp.shape[1]]
        for word in fp[:, cols]:
            ok = np.all(np.isfinite(word), axis=1)
            if ok.sum() >= min_row_instances:
                out.append(word[ok])
    return out


def _row_fits(pattern: Pattern, min_row_instances: int, floor: float
              ) -> list[tuple[np.ndarray, float, float]]:
    """Per row of at least ``min_row_instances`` instances: its middle (2,) (mean of the
    instance centres, pixels), its direction angle (radians, the line-weighted mean of
    its lines' angles) and that angle's standard error (radians: the median of its
    lines', each from its points' residual, at least ``floor`` pixels)."""
    rows = [[int(i) for i in r if 0 <= int(i) < len(pattern.instances)]
            for r in (pattern.extra.get("rows") or [])]
    out = []
    for r in rows:
        if len(r) < min_row_instances:
            continue
        one = Pattern(pattern.id, pattern.score, pattern.instances,
                      pattern.feature_points, extra={"rows": [r]})
        fits = [_fit_line(p) for p in pattern_lines(one, min_row_instances)]
        ref = fits[0][1]  # the instance-centre line
        ang, sig = [], []
        for _, d, resid, spread in fits:
            d = d if d @ ref >= 0 else -d
            ang.append(np.arctan2(d[1], d[0]))
            sig.append(max(resid, floor) / max(spread, 1e-9))
        ang_a, sig_a = np.unwrap(np.array(ang)), np.array(sig)
        wgt = 1.0 / sig_a ** 2
        out.append((fits[0][0], float((wgt * ang_a).sum() / wgt.sum()), float(np.median(sig_a))))
    return out


def _fold(a: np.ndarray) -> np.ndarray:
    """Angles (radians) folded into [-pi/2, pi/2) (a line has no sign)."""
    return (a + np.pi / 2) % np.pi - np.pi / 2


def pattern_vp_evidence(pattern: Pattern, params: ClaimParams = ClaimParams()
                        ) -> tuple[str, dict[str, Any]]:
    """Whether an RP's vanishing point is supported by its rows (module docstring).

    Each row of at least ``min_row_instances`` instances gives one line: through its
    instance centres, along the mean direction of its centre line and feature tracks.

    Returns
    -------
    status : str
        ``"supported"``, ``"frontal"`` (rows parallel within noise, or the VP at
        infinity), ``"too_few_rows"``, ``"inconsistent"`` (the rows do not meet at the VP)
        or ``"none"`` (``pattern.vanishing_point`` is None).
    evidence : dict
        ``rows`` used, ``spread_deg`` (range of the row directions), ``p_parallel``
        (chi-square p-value of "the rows are parallel"), ``residual_deg`` (largest angle
        between a row and the ray from its middle to the VP); only what was measured.
    """
    vp = pattern.vanishing_point
    boxes = np.array([i.bbox for i in pattern.instances], float).reshape(-1, 4)
    side = float(np.median(np.minimum(boxes[:, 2], boxes[:, 3]))) if len(boxes) else 0.0
    fits = _row_fits(pattern, params.min_row_instances, params.point_noise * max(side, 1e-6))
    ev: dict[str, Any] = {"rows": len(fits)}
    if vp is None:
        return "none", ev
    if len(fits) < params.min_rows:
        return _one_row_evidence(pattern, vp, params, side, ev)
    ang = np.array([a for _, a, _ in fits])
    ang = _fold(ang - ang[0]) + ang[0]
    sig = np.array([s for _, _, s in fits])
    wgt = 1.0 / sig ** 2
    mean = float((wgt * ang).sum() / wgt.sum())
    chi2 = float((((ang - mean) / sig) ** 2).sum())
    p_par = _chi2_sf(chi2, len(ang) - 1)
    spread_deg = float(np.degrees(np.ptp(ang)))
    ev.update(spread_deg=round(spread_deg, 3), p_parallel=round(p_par, 6))
    hx, hy, hw = (float(v) for v in vp.homogeneous)
    if (p_par >= params.parallel_alpha or spread_deg < params.min_convergence_deg
            or abs(hw) < 1e-12):
        return "frontal", ev
    res = []
    for (mid, a, _) in fits:
        ray = np.array([hx / hw, hy / hw]) - mid
        ray = ray / (np.linalg.norm(ray) + 1e-12)
        res.append(np.degrees(np.arcsin(min(1.0, abs(np.cos(a) * ray[1] - np.sin(a) * ray[0])))))
    ev["residual_deg"] = round(float(max(res)), 3)
    if ev["residual_deg"] > params.max_residual_deg:
        return "inconsistent", ev
    return "supported", ev


def _one_row_evidence(pattern: Pattern, vp: VanishingPoint, params: ClaimParams,
                      side: float, ev: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """An RP with fewer than ``min_rows`` rows: its longest row's lines (centre line and
    at least two feature tracks of ``min_row_instances`` points) must converge beyond
    noise (the same tests as rows) and every one meet the VP; else ``too_few_rows``."""
    rows = [[int(i) for i in r if 0 <= int(i) < len(pattern.instances)]
            for r in (pattern.extra.get("rows") or [])]
    rows = [r for r in rows if len(r) >= params.min_row_instances]
    if not rows:
        return "too_few_rows", ev
    one = Pattern(pattern.id, pattern.score, pattern.instances, pattern.feature_points,
                  extra={"rows": [max(rows, key=len)]})
    fits = [_fit_line(p) for p in pattern_lines(one, params.min_row_instances)]
    if len(fits) < 3:
        return "too_few_rows", ev
    floor = params.point_noise * max(side, 1e-6)
    ref = fits[0][1]
    ang, sig = [], []
    for _, d, resid, spread in fits:
        d = d if d @ ref >= 0 else -d
        ang.append(np.arctan2(ref[0] * d[1] - ref[1] * d[0], ref @ d))
        sig.append(max(resid, floor) / max(spread, 1e-9))
    ang_a, sig_a = np.array(ang), np.array(sig)
    wgt = 1.0 / sig_a ** 2
    mean = float((wgt * ang_a).sum() / wgt.sum())
    p_par = _chi2_sf(float((((ang_a - mean) / sig_a) ** 2).sum()), len(ang_a) - 1)
    spread_deg = float(np.degrees(np.ptp(ang_a)))
    ev.update(tracks=len(fits), spread_deg=round(spread_deg, 3), p_parallel=round(p_par, 6))
    hx, hy, hw = (float(v) for v in vp.homogeneous)
    if p_par >= params.parallel_alpha or spread_deg < params.min_convergence_deg or abs(hw) < 1e-12:
        return "frontal", ev
    res = []
    for mid, d, _, _ in fits:
        ray = np.array([hx / hw, hy / hw]) - mid
        ray = ray / (np.linalg.norm(ray) + 1e-12)
        res.append(np.degrees(np.arcsin(min(1.0, abs(d[0] * ray[1] - d[1] * ray[0])))))
    ev["residual_deg"] = round(float(max(res)), 3)
    return ("inconsistent" if ev["residual_deg"] > params.max_residual_deg
            else "supported"), ev


# ----------------------------------------------------------------------------- image VPs
def convergence_deg(homogeneous: Any, size: tuple[int, int]) -> float:
    """Angle (degrees) that the image diagonal subtends at a VP: how much lines across
    the image converge towards it; 0 for a VP at infinity. ``homogeneous`` (3,) in
    original pixels, ``size`` (width, height) original pixels."""
    hx, hy, hw = (float(v) for v in homogeneous)
    if abs(hw) < 1e-12:
        return 0.0
    w, h = size
    dist = float(np.hypot(hx / hw - w / 2.0, hy / hw - h / 2.0))
    return float(np.degrees(2.0 * np.arctan2(np.hypot(w, h) / 2.0, dist)))


#: The inlier angle of ``vp_lines`` written before it was recorded there, degrees (the
#: joint estimator's ``refine_angle_deg`` then).
DEFAULT_INLIER_ANGLE_DEG = 2.0


def line_nfa(k: int, n: int, angle_deg: float) -> float:
    """Number of false alarms of a point that ``k`` of ``n`` lines pass within
    ``angle_deg`` of: ``n (n - 1) (n - 2) / 2 x P[Binomial(n, 2 angle / 180) >= k]``
    (lines of independent uniform directions; the joint estimator proposes a Manhattan
    frame from each triplet of lines, :mod:`rescu.scene.vp.manhattan`).

    >>> line_nfa(112, 298, 2.0) < 1e-50      # a street: 112 of 298 segments
    True
    >>> line_nfa(10, 100, 2.0) > 1           # 10 of 100 edges of cells: chance
    True
    """
    from scipy.special import bdtrc

    n, k = max(int(n), 0), int(k)
    p = min(1.0, 2.0 * float(angle_deg) / 180.0)
    tail = 1.0 if k <= 0 else float(bdtrc(k - 1, n, p)) if k <= n else 0.0
    return max(n * (n - 1) * (n - 2) / 2.0, 1.0) * tail


def image_vp_evidence(v: dict[str, Any], size: tuple[int, int],
                      params: ClaimParams = ClaimParams(),
                      lines: dict[str, Any] | None = None, rows_count: bool = True
                      ) -> tuple[str, float]:
    """``("supported" | "at_infinity" | "weak", nfa)`` for one entry of the joint
    estimator's ``vanishing_points`` (``homogeneous``, ``support``, ``cues``); see the
    module docstring.

    ``lines`` is the result's ``vp_lines`` (``lines``, ``rp_rows``, ``inlier_angle_deg``;
    None: the VP's own inliers are all the lines there were). With ``rows_count`` the
    VP's inliers and the lines are those of every cue, RP rows included; without (no RP's
    own VP passed its test) its LSD segments alone."""
    cues = v.get("cues") or {}
    lines = lines or {}
    angle = float(lines.get("inlier_angle_deg", DEFAULT_INLIER_ANGLE_DEG))
    if rows_count:
        k = int(v.get("support", 0))
        n = int(lines.get("lines", 0)) + int(lines.get("rp_rows", 0)) if lines else k
    else:
        k = int(cues.get("lines", v.get("support", 0)))
        n = int(lines.get("lines", 0)) if lines else k
    nfa = line_nfa(k, max(n, k), angle)
    if k < params.min_image_support or nfa > params.max_image_nfa:
        return "weak", nfa
    if convergence_deg(v.get("homogeneous", [0, 0, 0]), size) < params.min_image_convergence_deg:
        return "at_infinity", nfa
    return "supported", nfa


def at_infinity(v: dict[str, Any]) -> dict[str, Any]:
    """A VP entry moved to infinity along its image direction (``w = 0``, unit ``x, y``;
    a 3D ``direction`` made parallel to the image plane alike)."""
    hx, hy, _ = (float(c) for c in v["homogeneous"])
    nrm = float(np.hypot(hx, hy)) or 1.0
    out = {**v, "homogeneous": [hx / nrm, hy / nrm, 0.0], "inside_image": False}
    if v.get("direction") is not None:
        dx, dy, _ = (float(c) for c in v["direction"])
        dn = float(np.hypot(dx, dy)) or 1.0
        out["direction"] = [dx / dn, dy / dn, 0.0]
    return out


def ts_status(pattern: Pattern) -> str:
    """``"equal_spacing"``, ``"unequal_spacing"`` or ``"too_few_instances"`` (no row
    long enough for the cross-ratio test)."""
    ts = pattern.translation_symmetry
    if ts is None:
        return "too_few_instances"
    return "equal_spacing" if ts.detected else "unequal_spacing"


def supported_claims(result: ImageResult, params: ClaimParams = ClaimParams()) -> ImageResult:
    """A copy of ``result`` that claims only what passes the tests (module docstring).

    Parameters
    ----------
    result : ImageResult
        The joint step's result (patterns with ``rows``; ``vanishing_points``), original
        pixels.
    params : ClaimParams

    Returns
    -------
    ImageResult
        Unsupported VPs set to None (patterns, image) or moved to
        ``rejected_vanishing_points``; ``vp_status`` (image and patterns),
        ``vp_evidence`` and ``ts_status`` (patterns) added. ``result`` is not modified.
    """
    res = ImageResult.from_json(copy.deepcopy(result.to_json()))
    any_supported = False
    statuses = []
    for p in res.patterns:
        st, ev = pattern_vp_evidence(p, params)
        if st != "supported":
            p.vanishing_point = None
        any_supported |= st == "supported"
        statuses.append(st)
        p.extra["vp_status"], p.extra["vp_evidence"] = st, ev
        p.extra["ts_status"] = ts_status(p)
    size = (int(res.width), int(res.height))
    listed = res.extra.get("vanishing_points")
    if listed:
        finite, far, rejected = [], [], []
        for v in listed:
            st, nfa = image_vp_evidence(v, size, params, res.extra.get("vp_lines"),
                                        rows_count=any_supported)
            nfa_r = float(f"{nfa:.3g}")
            if st == "supported":
                finite.append({**v, "nfa": nfa_r})
            elif st == "at_infinity":
                far.append({**at_infinity(v), "nfa": nfa_r, "status": st})
            else:
                rejected.append({**v, "nfa": nfa_r, "status": st})
        kept = finite + far
        res.extra["vanishing_points"] = kept
        res.extra["rejected_vanishing_points"] = rejected
        if kept:
            res.vanishing_point = VanishingPoint.from_json(kept[0])
            status = "supported" if finite else "frontal"
        else:
            res.vanishing_point = None
            status = "weak"
    elif res.vanishing_point is not None:  # RP-only: supported when an RP's VP is
        status = "supported" if any_supported else (
            "frontal" if "frontal" in statuses else "weak")
        if not any_supported:
            res.vanishing_point = None
    else:
        status = "none"
    res.extra["vp_status"] = status
    return res
