"""Claims with support: which vanishing points and symmetries a result may state.

The estimators of the scene step always return their best answer: a VP from three
nearly parallel feature tracks, or from a third Manhattan direction that a frontal scan
of coins does not have. :func:`supported_claims` (the caption step, before the caption
is written) keeps a claim only when its evidence passes a test, and otherwise says in
the JSON which test failed:

* **An RP's vanishing point** needs lines through at least ``min_row_instances``
  instances of a row (the feature tracks of one visual word along the row, and the line
  through the row's instance centres), at least ``min_lines`` of them from at least
  ``min_rows`` rows, that are *not parallel within noise*: their directions differ by
  more than a chi-square test at level ``parallel_alpha`` allows for points of noise
  ``point_noise`` x the median instance side, and by at least ``min_convergence_deg``;
  and the VP must lie on them (median angle between a line and the ray from its middle
  to the VP below ``max_residual_deg``). Pattern keys: ``vp_status`` (``"supported"``,
  ``"frontal"``: lines parallel, ``"too_few_rows"``, ``"inconsistent"``: the lines do
  not meet at the VP, ``"none"``: no VP was estimated) and ``vp_evidence`` (the
  measured numbers).
* **The image's vanishing points** (``vanishing_points`` of the joint estimator) each
  need ``min_image_support`` inlier lines and a finite point at which the image
  diagonal subtends at least ``min_image_convergence_deg`` (lines across the image that
  converge less than that are parallel in the picture: a frontal view). Those that fail
  move to ``rejected_vanishing_points`` with a ``status`` (``"at_infinity"``,
  ``"weak"``); ``vanishing_point`` is the first supported one (dominant first), or null
  with the image's ``vp_status``: ``"frontal"`` (every VP found lies at infinity),
  ``"weak"`` (too few lines), ``"none"`` (no VP from any cue). Without the joint list
  (fewer than three lines) the RP-only VP is kept when an RP's VP is supported.
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


@dataclass(frozen=True)
@config_section("scene", "claims")
class ClaimParams:
    """Tests a claim must pass (config section ``scene.claims``; module docstring).

    Attributes
    ----------
    min_row_instances : int
        A line counts when it passes through at least this many instances of one row.
    min_rows : int
        Fewest rows that give lines for an RP's VP.
    min_lines : int
        Fewest lines for an RP's VP.
    point_noise : float
        Noise floor of a line point, as a fraction of the median instance side.
    parallel_alpha : float
        Level of the chi-square test "the lines are parallel", (0, 1).
    min_convergence_deg : float
        Smallest spread of the line directions for a VP, degrees.
    max_residual_deg : float
        Largest median angle between a line and the ray from its middle to the VP, degrees.
    min_image_support : int
        Fewest inlier lines of one of the image's VPs.
    min_image_convergence_deg : float
        Smallest angle the image diagonal subtends at one of the image's VPs, degrees.
    """

    min_row_instances: int
    min_rows: int
    min_lines: int
    point_noise: float
    parallel_alpha: float
    min_convergence_deg: float
    max_residual_deg: float
    min_image_support: int
    min_image_convergence_deg: float

    def __post_init__(self) -> None:
        if int(self.min_row_instances) < 3:
            raise ValueError("ClaimParams.min_row_instances must be >= 3 (a line through "
                             "two points has no residual)")
        if int(self.min_rows) < 1 or int(self.min_lines) < 2:
            raise ValueError("ClaimParams.min_rows must be >= 1 and min_lines >= 2")
        if not 0.0 < float(self.parallel_alpha) < 1.0:
            raise ValueError(f"ClaimParams.parallel_alpha must be in (0, 1), got "
                             f"{self.parallel_alpha}")
        if float(self.point_noise) <= 0 or float(self.max_residual_deg) <= 0:
            raise ValueError("ClaimParams.point_noise and max_residual_deg must be > 0")

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


def _rows_with(pattern: Pattern, k: int) -> int:
    n = len(pattern.instances)
    return sum(1 for r in (pattern.extra.get("rows") or [])
               if sum(1 for i in r if 0 <= int(i) < n) >= k)


def pattern_vp_evidence(pattern: Pattern, params: ClaimParams = ClaimParams()
                        ) -> tuple[str, dict[str, Any]]:
    """Whether an RP's vanishing point is supported by its rows (module docstring).

    Returns
    -------
    status : str
        ``"supported"``, ``"frontal"``, ``"too_few_rows"``, ``"inconsistent"`` or
        ``"none"`` (``pattern.vanishing_point`` is None).
    evidence : dict
        ``rows`` and ``lines`` used, ``spread_deg`` (range of the line directions),
        ``p_parallel`` (chi-square p-value of "parallel"), ``residual_deg`` (median angle
        between a line and the ray to the VP); only what was measured.
    """
    vp = pattern.vanishing_point
    n_rows = _rows_with(pattern, params.min_row_instances)
    ev: dict[str, Any] = {"rows": n_rows}
    if vp is None:
        return "none", ev
    sets = pattern_lines(pattern, params.min_row_instances)
    ev["lines"] = len(sets)
    if n_rows < params.min_rows or len(sets) < params.min_lines:
        return "too_few_rows", ev
    boxes = np.array([i.bbox for i in pattern.instances], float)
    side = float(np.median(np.minimum(boxes[:, 2], boxes[:, 3])))
    floor = params.point_noise * max(side, 1e-6)
    fits = [_fit_line(p) for p in sets]
    ref = fits[int(np.argmax([f[3] for f in fits]))][1]
    theta, sigma = [], []
    for mid, d, resid, spread in fits:
        if d @ ref < 0:
            d = -d
        theta.append(np.arctan2(ref[0] * d[1] - ref[1] * d[0], ref @ d))
        sigma.append(max(resid, floor) / max(spread, 1e-9))  # slope SE, radians
    theta_a, sig = np.array(theta), np.array(sigma)
    wgt = 1.0 / sig ** 2
    mean = float((wgt * theta_a).sum() / wgt.sum())
    chi2 = float((((theta_a - mean) / sig) ** 2).sum())
    from scipy.stats import chi2 as _chi2

    p_par = float(_chi2.sf(chi2, len(theta_a) - 1))
    spread_deg = float(np.degrees(np.ptp(theta_a)))
    ev.update(spread_deg=round(spread_deg, 3), p_parallel=round(p_par, 6))
    if p_par >= params.parallel_alpha or spread_deg < params.min_convergence_deg:
        return "frontal", ev
    hx, hy, hw = (float(v) for v in vp.homogeneous)
    res = []
    for mid, d, _, _ in fits:
        ray = (np.array([hx / hw, hy / hw]) - mid) if abs(hw) > 1e-12 else np.array([hx, hy])
        ray = ray / (np.linalg.norm(ray) + 1e-12)
        res.append(np.degrees(np.arcsin(min(1.0, abs(d[0] * ray[1] - d[1] * ray[0])))))
    ev["residual_deg"] = round(float(np.median(res)), 3)
    if ev["residual_deg"] > params.max_residual_deg:
        return "inconsistent", ev
    return "supported", ev


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


def image_vp_status(v: dict[str, Any], size: tuple[int, int],
                    params: ClaimParams = ClaimParams()) -> str:
    """``"supported"``, ``"at_infinity"`` or ``"weak"`` for one entry of the joint
    estimator's ``vanishing_points`` (``homogeneous``, ``support``)."""
    if convergence_deg(v.get("homogeneous", [0, 0, 0]), size) < params.min_image_convergence_deg:
        return "at_infinity"
    if int(v.get("support", 0)) < params.min_image_support:
        return "weak"
    return "supported"


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
        kept, rejected = [], []
        for v in listed:
            st = image_vp_status(v, size, params)
            (kept if st == "supported" else rejected).append(v if st == "supported"
                                                             else {**v, "status": st})
        res.extra["vanishing_points"] = kept
        res.extra["rejected_vanishing_points"] = rejected
        if kept:
            res.vanishing_point = VanishingPoint.from_json(kept[0])
            status = "supported"
        else:
            res.vanishing_point = None
            status = ("frontal" if all(r["status"] == "at_infinity" for r in rejected)
                      else "weak")
    elif res.vanishing_point is not None:  # RP-only: supported when an RP's VP is
        status = "supported" if any_supported else (
            "frontal" if "frontal" in statuses else "weak")
        if not any_supported:
            res.vanishing_point = None
    else:
        status = "none"
    res.extra["vp_status"] = status
    return res
