"""Vanishing-point detection (VPD) from recurring patterns, a line baseline, and VP errors.

RP-based VPD (no explicit lines)
--------------------------------
When the instances of an RP recur along a line in 3D, the corresponding features of
one visual word across the instances lie on an *implicit line* in the image, and the
implicit lines of all visual words (and of all parallel rows of the RP) meet at the
vanishing point (VP) of the recurrence direction.

1. :func:`rescu.layout.group_rows` orders the instances into collinear *rows* (greedy multi-line
   search on the instance centres; the longest rows first, and later rows may not cross
   earlier ones, so that a grid yields its rows *or* its columns, never a mix, and no
   diagonals).
2. :func:`pattern_lines` fits one implicit line (total least squares) per visual word
   and row; a row with no usable feature gives the line through its instance centres.
3. :func:`ransac_vp` hypothesises a VP from every pair of lines (all pairs when there are
   at most ``ransac_iterations`` of them, else that many random pairs drawn from
   ``seed``) and, so that a frontal view is represented, the point at infinity along
   every line. The *angular constraint* (AC) refuses pairs of lines closer to parallel
   than ``ac_threshold_deg``: their intersection is ill-conditioned. A line is an inlier
   of a VP when the angle between the line and the direction from its midpoint to the
   VP is below ``inlier_angle_deg``. The hypothesis with the largest (weighted) support
   is refined by iteratively reweighted least squares of the sines of those angles, and
   replaced by the point at infinity when an F-test (level ``infinity_alpha``) cannot
   tell the finite fit from the best fit at infinity.
4. Where the lines carry their feature points (implicit lines always do),
   :func:`ml_refine_vp` finishes with the maximum-likelihood VP: every feature track
   gets its own line through the VP and the squared orthogonal distances of all the
   points are minimised (``ml_refine``). Rows that pass the translation-symmetry test
   also constrain the VP by their spacing (:func:`spacing_refine_vp`: equally spaced
   3D instances, so the image spacing shrinks towards the VP; accepted by a
   likelihood-ratio test of level ``spacing_alpha``). The infinity decision is then a
   point-level F-test (:func:`ml_infinity_test`, noise floor ``infinity_noise_px``)
   instead of the line-level one, which has only (lines - 2) degrees of freedom.
5. :func:`joint_vanishing_point` re-estimates a VP on the tracks of several patterns
   that share it (likelihood-ratio test of level ``joint_alpha``); the scene step uses
   it for the image's dominant VP.

All estimation runs in normalised coordinates (image centre at 0, (W + H) / 2 pixels to
1); a VP is returned as a unit-norm homogeneous point in original pixels, ``w = 0`` for a
point at infinity.

Line baseline
-------------
:func:`line_vanishing_point`: LSD line segments (``cv2.createLineSegmentDetector``)
longer than ``lsd_min_length`` x the image diagonal, then the same RANSAC with the
segment lengths as weights (a stand-in for Zhou, Farhat and Wang 2017). The dominant VP
(largest inlier length) is returned.

Evaluation
----------
:func:`point_error`, :func:`vector_error` (the paper's two VP errors),
:func:`closest_gt_error` (with several ground-truth VPs, the error to the closest one),
:func:`success_rate` and :func:`paired_test`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..layout import checked_points, fit_line, pattern_rows
from ..types import VanishingPoint
from ..params import params_from_dict

# |w| of a unit-norm homogeneous pixel point below which it is "at infinity" for the
# error measures (|w| = 1e-12 is a point about 1e12 pixels away).
INFINITY_EPS = 1e-12


@dataclass(frozen=True)
class VPParams:
    """Parameters of vanishing-point detection (RP-based and line baseline).

    Attributes
    ----------
    ransac_iterations : int
        Line pairs hypothesised (all pairs when there are fewer).
    inlier_angle_deg : float
        A line supports a VP when its angle to the direction towards the VP is below this.
    ac_threshold_deg : float
        Angular constraint: pairs of lines closer to parallel than this hypothesise no VP.
    min_lines : int
        Fewest lines (and fewest inliers) for a VP.
    infinity_alpha : float
        Level of the F-test that snaps a VP to infinity when the data cannot tell it
        from a point at infinity; 0 disables snapping.
    infinity_noise_deg : float
        Floor of the per-line angular noise in that F-test (degrees): the noise of the
        lines of one instance is correlated (instance deformation, localisation), so
        the residual of the finite fit underestimates it.
    infinity_noise_px : float
        Floor of the feature noise (pixels) in the point-level infinity test on feature
        tracks (:func:`ml_infinity_test`), which replaces the line-level test when the
        lines carry their points.
    row_tolerance : float
        An instance centre belongs to a row when it lies within this fraction of the
        instance's smaller box side from the row line.
    min_row_instances : int
        Fewest instances in a row (a pattern of exactly 2 instances is one row).
    max_line_residual : float
        An implicit line whose RMS residual exceeds this fraction of the median instance
        size is dropped (feature mismatch).
    precision_floor_px : float
        Implicit lines are weighted in the refinement by their inverse angular variance
        (spread^2 / max(residual, this)^2); 0 weighs all lines equally.
    lsd_min_length : float
        Baseline: shortest LSD segment kept, as a fraction of the image diagonal.
    lsd_max_segments : int
        Baseline: the longest this many segments are kept.
    ml_refine : bool
        Finish the fit with the maximum-likelihood VP (:func:`ml_refine_vp`) on the
        feature tracks of the inlier lines, where the lines carry their points.
    register_centres : bool
        Locate instances by their features (:func:`rescu.layout.registered_centres`) instead of
        their box centres for rows and the centre fallbacks, and leave duplicate
        instances (registered centres closer than half an instance) out of the rows.
    joint_alpha : float
        Level of the likelihood-ratio test that merges another pattern's feature tracks
        into the image VP of the dominant pattern (:func:`joint_vanishing_point`: the
        patterns share the VP unless the joint fit is significantly worse); 0: the
        image VP is the dominant pattern's own.
    spacing_alpha : float
        Level of the likelihood-ratio test that accepts the *spacing model* on rows that
        pass the translation-symmetry test (:func:`spacing_refine_vp`: equally spaced
        3D points, so the image spacing along the row also locates the VP); 0: off.
    seed : int
        Seed of the random pair sampling.
    """

    ransac_iterations: int = 1000
    inlier_angle_deg: float = 1.5
    ac_threshold_deg: float = 2.0
    min_lines: int = 3
    infinity_alpha: float = 0.01
    infinity_noise_deg: float = 0.5
    infinity_noise_px: float = 0.25
    row_tolerance: float = 0.25
    min_row_instances: int = 3
    max_line_residual: float = 0.15
    precision_floor_px: float = 1.0
    lsd_min_length: float = 0.025
    lsd_max_segments: int = 1500
    ml_refine: bool = True
    register_centres: bool = True
    joint_alpha: float = 0.01
    spacing_alpha: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.ransac_iterations < 1:
            raise ValueError("VPParams.ransac_iterations must be >= 1")
        if not 0 < self.inlier_angle_deg < 90:
            raise ValueError("VPParams.inlier_angle_deg must be in (0, 90)")
        if not 0 <= self.ac_threshold_deg < 90:
            raise ValueError("VPParams.ac_threshold_deg must be in [0, 90)")
        if self.min_lines < 2:
            raise ValueError("VPParams.min_lines must be >= 2")
        if not 0 <= self.infinity_alpha < 1:
            raise ValueError("VPParams.infinity_alpha must be in [0, 1)")
        if self.infinity_noise_px < 0:
            raise ValueError("VPParams.infinity_noise_px must be >= 0")
        if not 0 <= self.joint_alpha < 1:
            raise ValueError("VPParams.joint_alpha must be in [0, 1)")
        if not 0 <= self.spacing_alpha < 1:
            raise ValueError("VPParams.spacing_alpha must be in [0, 1)")
        if self.min_row_instances < 2:
            raise ValueError("VPParams.min_row_instances must be >= 2")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "VPParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


# ----------------------------------------------------------------------------- lines
@dataclass
class Lines:
    """A set of image lines (segments) in pixels.

    Attributes
    ----------
    midpoints : (L, 2) float
        A point on each line (segment midpoint / centroid of the fitted points), pixels.
    directions : (L, 2) float
        Unit direction of each line.
    weights : (L,) float
        Weight of each line in the support and the fit (1 for implicit lines, the
        length in pixels for segments).
    precision : (L,) float or None
        Extra weight of each line in the least-squares refinement only (inverse
        angular variance, relative); None: all 1.
    points : list of (K_l, 2) float arrays or None
        The image points each line was fitted to (pixels), for the maximum-likelihood
        refinement (:func:`ml_refine_vp`); None: unknown (e.g. LSD segments).
    positions : list of (K_l,) float arrays or None entries, or None
        For a line fitted to the features of one visual word along an *equally spaced*
        row: the ordinal of each point's instance in the row (0, 1, 2, ...; gaps where
        the word is missing), used by the spacing model (:func:`spacing_refine_vp`);
        None where the row is not known to be equally spaced.
    """

    midpoints: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    precision: np.ndarray | None = None
    points: list[np.ndarray] | None = None
    positions: list[np.ndarray | None] | None = None

    def __post_init__(self) -> None:
        self.midpoints = np.asarray(self.midpoints, float).reshape(-1, 2)
        self.directions = np.asarray(self.directions, float).reshape(-1, 2)
        n = len(self.midpoints)
        if self.directions.shape != (n, 2):
            raise ValueError(f"Lines.directions must have shape ({n}, 2), "
                             f"got {self.directions.shape}")
        self.weights = np.asarray(self.weights, float).reshape(-1)
        if self.weights.shape != (n,):
            raise ValueError(f"Lines.weights must have shape ({n},), got {self.weights.shape}")
        norm = np.linalg.norm(self.directions, axis=1, keepdims=True)
        self.directions = self.directions / np.where(norm > 0, norm, 1.0)
        self.precision = (np.ones(n) if self.precision is None
                          else np.asarray(self.precision, float).reshape(-1))
        if self.precision.shape != (n,):
            raise ValueError(f"Lines.precision must have shape ({n},), "
                             f"got {self.precision.shape}")
        if self.points is not None:
            if len(self.points) != n:
                raise ValueError(f"Lines.points must hold {n} arrays, got {len(self.points)}")
            self.points = [np.asarray(q, float).reshape(-1, 2) for q in self.points]
        if self.positions is not None:
            if self.points is None or len(self.positions) != n:
                raise ValueError(f"Lines.positions must hold {n} entries and needs points")
            self.positions = [None if k is None else np.asarray(k, float).reshape(-1)
                              for k in self.positions]
            for k, q in zip(self.positions, self.points):
                if k is not None and len(k) != len(q):
                    raise ValueError("Lines.positions: one ordinal per point")

    def __len__(self) -> int:
        return len(self.midpoints)

    @classmethod
    def empty(cls) -> "Lines":
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0,)))

    @classmethod
    def from_segments(cls, segments: np.ndarray) -> "Lines":
        """Lines from segments ``(L, 4)`` ``[x1, y1, x2, y2]`` pixels, weighted by length."""
        s = np.asarray(segments, float).reshape(-1, 4)
        d = s[:, 2:] - s[:, :2]
        return cls((s[:, :2] + s[:, 2:]) / 2, d, np.linalg.norm(d, axis=1))

    @classmethod
    def concat(cls, parts: Sequence["Lines"]) -> "Lines":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        pts = (None if any(p.points is None for p in parts)
               else [q for p in parts for q in p.points])
        pos = (None if pts is None or all(p.positions is None for p in parts)
               else [k for p in parts
                     for k in (p.positions if p.positions is not None else [None] * len(p))])
        return cls(np.concatenate([p.midpoints for p in parts]),
                   np.concatenate([p.directions for p in parts]),
                   np.concatenate([p.weights for p in parts]),
                   np.concatenate([p.precision for p in parts]), pts, pos)


def _chi2_ppf(q: float, df: float) -> float:
    """Quantile ``q`` of the chi-squared distribution with ``df`` degrees of freedom.

    What ``scipy.stats.chi2.ppf`` computes for 0 < q < 1, from ``scipy.special`` (whose
    import costs half of ``scipy.stats``'s, paid by every scene job).
    """
    from scipy.special import gammaincinv

    return float(2 * gammaincinv(df / 2, q))


def _f_ppf(q: float, dfn: float, dfd: float) -> float:
    """Quantile ``q`` of Fisher's F(dfn, dfd), as ``scipy.stats.f.ppf`` for 0 < q < 1."""
    from scipy.special import fdtri

    return float(fdtri(dfn, dfd, q))


# ----------------------------------------------------------------------------- rows


def pattern_lines(feature_points: np.ndarray | None, centres: np.ndarray,
                  rows: Sequence[np.ndarray], sizes: np.ndarray | None = None,
                  max_line_residual: float = 0.15, precision_floor_px: float = 1.0,
                  equal_rows: Sequence[bool] | None = None) -> Lines:
    """Implicit lines of an RP: one per visual word and row.

    Parameters
    ----------
    feature_points : (M, N', 2) float or None
        Corresponding feature positions, pixels, NaN where missing; column n belongs to
        instance n (N' may be smaller than the number of instances N: the later
        instances have no features).
    centres : (N, 2) float
        Instance centres, pixels.
    rows : list of int arrays
        Instance indices of each row, from :func:`rescu.layout.group_rows`.
    sizes : (N,) float or None
        Instance sizes, pixels (for the residual check; None: no check).
    max_line_residual : float
        Lines with RMS residual above this fraction of the median row instance size are
        dropped.
    precision_floor_px : float
        Noise floor (pixels) of the line precision weights of the refinement
        (:func:`_line_precision`); 0 gives all lines the same weight.
    equal_rows : list of bool or None
        Per row, whether it is equally spaced in 3D (translation symmetry): its feature
        lines then carry the instance ordinals of their points (``Lines.positions``).

    Returns
    -------
    Lines
        A word needs a finite point in at least min(3, row length) instances of the row.
        A row without any feature line gives the line through its instance centres.
    """
    c, fp = checked_points(centres, feature_points)
    mids, dirs, prec = [], [], []
    pts_used: list[np.ndarray] = []
    pos_used: list[np.ndarray | None] = []
    if equal_rows is not None and len(equal_rows) != len(rows):
        raise ValueError(f"equal_rows must have {len(rows)} entries, got {len(equal_rows)}")
    for r_i, row in enumerate(rows):
        row = np.asarray(row, int)
        equal = bool(equal_rows[r_i]) if equal_rows is not None else False
        need = min(3, len(row))
        scale = float(np.median(sizes[row])) if sizes is not None else np.inf
        got = 0
        if fp is not None and len(row) >= 2:
            pts = fp[:, row, :]  # (M, K, 2)
            fin = np.all(np.isfinite(pts), axis=2)
            for m in range(pts.shape[0]):
                q = pts[m][fin[m]]
                if len(q) < need:
                    continue
                if np.linalg.norm(q.max(axis=0) - q.min(axis=0)) <= 0:
                    continue
                cen, d, rms = fit_line(q)
                if rms > max_line_residual * scale:
                    continue
                mids.append(cen)
                dirs.append(d)
                prec.append(_line_precision(q, cen, d, rms, precision_floor_px))
                pts_used.append(q)
                pos_used.append(np.nonzero(fin[m])[0].astype(float) if equal else None)
                got += 1
        if got == 0 and len(row) >= 2:
            cen, d, rms = fit_line(c[row])
            if rms <= max_line_residual * scale or len(row) == 2:
                mids.append(cen)
                dirs.append(d)
                prec.append(_line_precision(c[row], cen, d, rms, precision_floor_px))
                pts_used.append(c[row])
                pos_used.append(np.arange(len(row), dtype=float) if equal else None)
    if not mids:
        return Lines.empty()
    p = np.array(prec)
    return Lines(np.array(mids), np.array(dirs), np.ones(len(mids)), p / p.mean(),
                 pts_used, pos_used if any(k is not None for k in pos_used) else None)


def _line_precision(q: np.ndarray, cen: np.ndarray, d: np.ndarray, rms: float,
                    floor_px: float) -> float:
    """Inverse angular variance of a TLS line: sum of squared spreads / noise variance.

    The noise is the RMS residual (floored at ``floor_px``); var(angle) ~ sigma^2 /
    sum_k ((q_k - centroid) . d)^2.
    """
    if floor_px <= 0:
        return 1.0
    t = (q - cen) @ d
    return float((t ** 2).sum() / max(rms, floor_px) ** 2)


# ----------------------------------------------------------------------------- RANSAC
def _normaliser(image_size: tuple[int, int]) -> np.ndarray:
    w, h = float(image_size[0]), float(image_size[1])
    s = 2.0 / max(w + h, 1e-9)
    return np.array([[s, 0, -s * w / 2], [0, s, -s * h / 2], [0, 0, 1.0]])


def _sin_errors(v: np.ndarray, mids: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """|sin| of the angle between each line and the direction from its midpoint to VP(s).

    v : (3,) or (H, 3); returns (L,) or (H, L). 1 where the VP is on the midpoint.
    """
    v2 = np.atleast_2d(v)
    u = v2[:, None, :2] - v2[:, None, 2:3] * mids[None, :, :]  # (H, L, 2)
    cross = np.abs(dirs[None, :, 0] * u[..., 1] - dirs[None, :, 1] * u[..., 0])
    nu = np.linalg.norm(u, axis=2)
    out = np.where(nu > 1e-15, cross / np.where(nu > 1e-15, nu, 1.0), 1.0)
    return out[0] if np.ndim(v) == 1 else out


def _fit_vp(mids: np.ndarray, dirs: np.ndarray, w: np.ndarray, v0: np.ndarray,
            n_iter: int = 10) -> np.ndarray:
    """IRLS least squares of sum w_i sin^2(angle_i) over unit 3-vectors v (normalised px)."""
    nrm = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    lines = np.concatenate([nrm, -(nrm * mids).sum(axis=1, keepdims=True)], axis=1)  # l_i
    v = v0 / np.linalg.norm(v0)
    for _ in range(n_iter):
        u = v[:2][None, :] - v[2] * mids
        nu2 = np.maximum((u ** 2).sum(axis=1), 1e-12)
        ww = w / nu2  # l_i . v / |u_i| = sin(angle_i)
        a = (lines * ww[:, None]).T @ lines
        _, vecs = np.linalg.eigh(a)
        vn = vecs[:, 0]
        if vn @ v < 0:
            vn = -vn
        if np.linalg.norm(vn - v) < 1e-12:
            v = vn
            break
        v = vn
    return v


def _fit_infinity(dirs: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Direction (unit (x, y, 0)) minimising sum w_i sin^2 to the lines."""
    nrm = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    a = (nrm * w[:, None]).T @ nrm
    _, vecs = np.linalg.eigh(a)
    d = vecs[:, 0]
    return np.array([d[0], d[1], 0.0])


def _canonical(v: np.ndarray) -> np.ndarray:
    """Unit norm, sign fixed (w >= 0; for w = 0 the first nonzero coordinate > 0)."""
    v = np.asarray(v, float)
    v = v / np.linalg.norm(v)
    if v[2] < 0 or (v[2] == 0 and (v[0] < 0 or (v[0] == 0 and v[1] < 0))):
        v = -v
    return v + 0.0  # no negative zeros


def ransac_vp(lines: Lines, image_size: tuple[int, int], params: VPParams = VPParams(),
              ) -> VanishingPoint | None:
    """The VP with the largest support among the lines (RANSAC with the angular constraint).

    Parameters
    ----------
    lines : Lines
        Lines in pixels (of the image whose size is ``image_size``).
    image_size : (int, int)
        ``(width, height)`` in the same pixels; used for normalisation and ``inside_image``.
    params : VPParams

    Returns
    -------
    VanishingPoint or None
        Unit-norm homogeneous VP in the pixels of ``lines`` (``w = 0`` at infinity),
        ``support`` = number of inlier lines; None with fewer than ``min_lines`` lines or
        inliers.
    """
    if len(image_size) != 2 or min(image_size) <= 0:
        raise ValueError(f"image_size must be (width, height) > 0, got {image_size}")
    n = len(lines)
    if n < params.min_lines:
        return None
    t = _normaliser(image_size)
    mids = lines.midpoints * t[0, 0] + t[:2, 2]
    dirs = lines.directions
    w = lines.weights
    wf = lines.weights * lines.precision  # weights of the least-squares refinement
    nrm = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    homog = np.concatenate([nrm, -(nrm * mids).sum(axis=1, keepdims=True)], axis=1)

    # hypotheses: pairs of lines that pass the angular constraint (AC) ...
    n_pairs = n * (n - 1) // 2
    if n_pairs <= params.ransac_iterations:
        ii, jj = np.triu_indices(n, k=1)
    else:
        rng = np.random.default_rng(params.seed)
        ii = rng.integers(0, n, params.ransac_iterations)
        jj = rng.integers(0, n - 1, params.ransac_iterations)
        jj = jj + (jj >= ii)
    keep = ac_mask(dirs[ii], dirs[jj], params.ac_threshold_deg)
    hyp = np.cross(homog[ii[keep]], homog[jj[keep]])
    # ... and the points at infinity along the lines (frontal views)
    if n <= params.ransac_iterations:
        inf_idx = np.arange(n)
    else:
        inf_idx = np.random.default_rng(params.seed + 1).choice(n, params.ransac_iterations,
                                                                 replace=False)
    hyp = np.concatenate([hyp, np.concatenate([dirs[inf_idx], np.zeros((len(inf_idx), 1))],
                                              axis=1)])
    hn = np.linalg.norm(hyp, axis=1)
    hyp = hyp[hn > 1e-12] / hn[hn > 1e-12, None]
    if len(hyp) == 0:
        return None
    sin_thr = np.sin(np.radians(params.inlier_angle_deg))
    best_v, best_key = None, None
    for start in range(0, len(hyp), 256):
        h = hyp[start:start + 256]
        err = _sin_errors(h, mids, dirs)
        inl = err < sin_thr
        score = (inl * w[None, :]).sum(axis=1)
        resid = (np.where(inl, err ** 2, 0) * w[None, :]).sum(axis=1)
        for k in range(len(h)):
            key = (float(score[k]), -float(resid[k]))
            if best_key is None or key > best_key:
                best_key, best_v = key, h[k]
    assert best_v is not None
    v = best_v
    inl = _sin_errors(v, mids, dirs) < sin_thr
    for _ in range(5):  # refine on the inliers, re-select the inliers
        if inl.sum() < params.min_lines:
            return None
        v = _fit_vp(mids[inl], dirs[inl], wf[inl], v)
        new = _sin_errors(v, mids, dirs) < sin_thr
        if np.array_equal(new, inl):
            break
        inl = new
    if inl.sum() < params.min_lines:
        return None
    pts = None
    spaced = False
    if params.ml_refine and lines.points is not None:
        idx = np.nonzero(inl)[0]
        pts = [lines.points[i] * t[0, 0] + t[:2, 2] for i in idx]
        if all(len(q) >= 2 for q in pts):
            v_ml = ml_refine_vp(pts, v)
            # keep the ML point only if it leaves the inlier set intact
            if np.all(_sin_errors(v_ml, mids[inl], dirs[inl]) < sin_thr):
                v = v_ml
            pos = ([lines.positions[i] for i in idx] if lines.positions is not None
                   else [None] * len(idx))
            if params.spacing_alpha > 0 and any(k is not None and len(k) >= 3 for k in pos):
                v_sp = spacing_refine_vp(pts, pos, v, params.spacing_alpha,
                                         params.infinity_alpha,
                                         params.infinity_noise_px * t[0, 0])
                if v_sp is not None and (v_sp[2] == 0 or np.all(
                        _sin_errors(v_sp, mids[inl], dirs[inl]) < sin_thr)):
                    v, spaced = v_sp, True
        else:
            pts = None
    if spaced:
        pass  # spacing_refine_vp made the infinity decision
    elif pts is not None:
        v = ml_infinity_test(pts, v, params.infinity_alpha,
                             params.infinity_noise_px * t[0, 0])
    else:
        v = _maybe_infinity(v, mids[inl], dirs[inl], wf[inl], params.infinity_alpha,
                            params.infinity_noise_deg)
    v_px = np.linalg.solve(t, v)
    v_px = _canonical(v_px)
    return VanishingPoint(v_px, inside_image(v_px, image_size), int(inl.sum()))


def _track_costs(v: np.ndarray, scat: np.ndarray) -> np.ndarray:
    """Smallest sum of squared orthogonal distances of each track to a line through v.

    v : (3,) homogeneous point (finite or at infinity); scat : (T, 3, 3) sums of
    p~ p~^T over each track's points p~ = (x, y, 1). The line through v is
    l = B a with B a basis of v's orthogonal complement; the distance of p~ to l is
    l . p~ / |l_xy|, so the cost is the smallest generalised eigenvalue lambda of
    (B^T S B, B^T diag(1, 1, 0) B): a root of det(M - lambda N) = 0.
    """
    _, _, vt = np.linalg.svd(v.reshape(1, 3))
    b = vt[1:].T  # (3, 2)
    m = np.einsum("ia,tij,jb->tab", b, scat, b)
    nn = b[:2].T @ b[:2]
    qa = nn[0, 0] * nn[1, 1] - nn[0, 1] ** 2
    qb = -(m[:, 0, 0] * nn[1, 1] + m[:, 1, 1] * nn[0, 0] - 2 * m[:, 0, 1] * nn[0, 1])
    qc = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] ** 2
    disc = np.sqrt(np.maximum(qb ** 2 - 4 * qa * qc, 0.0))
    den = -qb + disc
    return np.where(den > 0, 2 * np.maximum(qc, 0.0) / np.where(den > 0, den, 1.0), 0.0)


def _padded_tracks(points: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracks as padded arrays: homogeneous points (T, K, 3) (zeros where padded), mask
    (T, K) and the unit normal of each track's free TLS line (T, 2) (sign reference)."""
    kmax = max(len(q) for q in points)
    ph = np.zeros((len(points), kmax, 3))
    mask = np.zeros((len(points), kmax), bool)
    ref = np.zeros((len(points), 2))
    for i, q in enumerate(points):
        q = np.asarray(q, float).reshape(-1, 2)
        ph[i, :len(q), :2] = q
        ph[i, :len(q), 2] = 1.0
        mask[i, :len(q)] = True
        d = fit_line(q)[1] if len(q) >= 2 else np.array([1.0, 0.0])
        ref[i] = [-d[1], d[0]]
    return ph, mask, ref


def _track_residuals(v: np.ndarray, ph: np.ndarray, mask: np.ndarray,
                     ref: np.ndarray) -> np.ndarray:
    """Signed orthogonal distances (T, K) of the track points to each track's best line
    through v (0 where padded); their squares sum to :func:`_track_costs`."""
    _, _, vt = np.linalg.svd(v.reshape(1, 3))
    b = vt[1:].T  # (3, 2)
    scat = np.einsum("tki,tkj->tij", ph, ph)
    m = np.einsum("ia,tij,jb->tab", b, scat, b)
    nn = b[:2].T @ b[:2]
    qa = nn[0, 0] * nn[1, 1] - nn[0, 1] ** 2
    qb = -(m[:, 0, 0] * nn[1, 1] + m[:, 1, 1] * nn[0, 0] - 2 * m[:, 0, 1] * nn[0, 1])
    qc = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] ** 2
    disc = np.sqrt(np.maximum(qb ** 2 - 4 * qa * qc, 0.0))
    den = -qb + disc
    lam = np.where(den > 0, 2 * np.maximum(qc, 0.0) / np.where(den > 0, den, 1.0), 0.0)
    r = m - lam[:, None, None] * nn[None]  # (T, 2, 2), singular: a spans its null space
    a1 = np.stack([-r[:, 0, 1], r[:, 0, 0]], axis=1)
    a2 = np.stack([-r[:, 1, 1], r[:, 1, 0]], axis=1)
    a = np.where((np.linalg.norm(a1, axis=1) >= np.linalg.norm(a2, axis=1))[:, None], a1, a2)
    line = a @ b.T  # (T, 3)
    nrm = np.linalg.norm(line[:, :2], axis=1)
    ok = nrm > 1e-15
    line = line / np.where(ok, nrm, 1.0)[:, None]
    sign = np.where((line[:, :2] * ref).sum(axis=1) < 0, -1.0, 1.0)
    line = line * sign[:, None]
    d = np.einsum("tki,ti->tk", ph, line)
    return np.where(mask & ok[:, None], d, 0.0)


def ml_refine_vp(points: Sequence[np.ndarray], v0: np.ndarray,
                 weights: np.ndarray | None = None, noise_floor: float = 0.0,
                 ) -> np.ndarray:
    """Maximum-likelihood VP of feature tracks (implicit lines) from a starting point.

    Minimises sum_t w_t / sigma_t^2 * min_{l through v} sum_k d(p_tk, l)^2 over
    homogeneous v: every track t (the features of one visual word along one row) is
    explained by its own line through the VP, and the cost is the squared orthogonal
    distance of its points to that line (isotropic Gaussian feature noise). sigma_t is
    the track's own RMS residual of a free line fit, floored at ``noise_floor``
    (``noise_floor`` = 0: sigma_t = 1, all points weighted equally). Unlike the
    sine-of-angle fit it accounts for the noise of the track centroids, which matters
    when the VP is near the pattern.

    Parameters
    ----------
    points : list of (K_t, 2) float, K_t >= 2
        The points of each track, in the (normalised) coordinates of ``v0``.
    v0 : (3,) float
        Starting homogeneous VP (e.g. the RANSAC + IRLS estimate).
    weights : (T,) float or None
        Extra weight of each track (None: 1).
    noise_floor : float
        Floor of sigma_t, same units as the points.

    Returns
    -------
    (3,) float
        Unit-norm homogeneous VP (``v0`` when the optimisation fails).
    """
    from scipy.optimize import least_squares

    v0 = np.asarray(v0, float)
    v0 = v0 / np.linalg.norm(v0)
    if len(points) < 2:
        return v0
    w = np.ones(len(points)) if weights is None else np.asarray(weights, float).reshape(-1)
    if noise_floor > 0:
        for i, q in enumerate(points):
            _, _, rms = fit_line(np.asarray(q, float).reshape(-1, 2))
            w[i] = w[i] / max(rms, noise_floor) ** 2
    ph, mask, ref = _padded_tracks(points)
    sw = np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(v0.reshape(1, 3))
    u = vt[1:].T  # tangent basis at v0

    def vec(x: np.ndarray) -> np.ndarray:
        v = v0 + u @ x
        return v / np.linalg.norm(v)

    def resid(x: np.ndarray) -> np.ndarray:
        return (sw * _track_residuals(vec(x), ph, mask, ref))[mask]

    if int(mask.sum()) < 2:
        return v0
    try:
        sol = least_squares(resid, np.zeros(2), method="lm", xtol=1e-14, ftol=1e-14,
                            gtol=1e-14)
    except (ValueError, np.linalg.LinAlgError):
        return v0
    if not np.all(np.isfinite(sol.x)) or (resid(sol.x) ** 2).sum() > (resid(np.zeros(2)) ** 2).sum():
        return v0
    return vec(sol.x)


def _track_scatter(points: Sequence[np.ndarray]) -> tuple[np.ndarray, int]:
    """(T, 3, 3) sums of p~ p~^T of each track and the total number of points."""
    scat = np.zeros((len(points), 3, 3))
    n = 0
    for i, q in enumerate(points):
        ph = np.c_[np.asarray(q, float).reshape(-1, 2), np.ones(len(q))]
        scat[i] = ph.T @ ph
        n += len(q)
    return scat, n


def ml_infinity_test(points: Sequence[np.ndarray], v: np.ndarray, alpha: float,
                     noise_floor: float = 0.0) -> np.ndarray:
    """Replace a finite ML VP by the ML point at infinity when an F-test cannot tell them apart.

    Point-level test on the feature tracks (same cost as :func:`ml_refine_vp`, all
    points weighted equally): C = sum of squared orthogonal distances of the points to
    their track's line through the VP; F = (C_inf - C_fin) / sigma^2 with
    sigma^2 = max(C_fin / dof, noise_floor^2), dof = P - T - 2 (P points, T tracks:
    one angle per track and two VP coordinates). Snap when F is below the
    (1 - alpha) quantile of F(1, dof) (of chi^2(1) when sigma^2 is the floor). Unlike the
    line-level test (:func:`_maybe_infinity`, dof = T - 2) it keeps the power of all
    the points, so a single row of five tracks is not pushed to infinity.

    Parameters
    ----------
    points : list of (K_t, 2) float
        Track points (normalised coordinates, like ``v``).
    v : (3,) float
        The finite ML VP.
    alpha : float
        Test level; 0: never snap.
    noise_floor : float
        Floor of the point noise sigma, same units as the points.

    Returns
    -------
    (3,) float
        ``v`` or the ML point at infinity ``(dx, dy, 0)``.
    """
    v = np.asarray(v, float)
    if alpha <= 0 or v[2] == 0 or len(points) < 2:
        return v
    from scipy.optimize import minimize_scalar

    scat, n_pts = _track_scatter(points)
    c_fin = float(_track_costs(v, scat).sum())
    # ML point at infinity: start from the mean track direction (sign-free average)
    dirs = np.array([fit_line(q)[1] for q in points])
    d0 = _fit_infinity(dirs, np.ones(len(dirs)))[:2]
    th0 = float(np.arctan2(d0[1], d0[0]))

    def cost_inf(th: float) -> float:
        return float(_track_costs(np.array([np.cos(th), np.sin(th), 0.0]), scat).sum())

    r = minimize_scalar(cost_inf, bounds=(th0 - 0.3, th0 + 0.3), method="bounded",
                        options={"xatol": 1e-10})
    th = float(r.x) if cost_inf(float(r.x)) <= cost_inf(th0) else th0
    c_inf = cost_inf(th)
    v_inf = np.array([np.cos(th), np.sin(th), 0.0])
    dof = n_pts - len(points) - 2
    floor2 = noise_floor ** 2
    sigma2 = max(c_fin / dof if dof > 0 else 0.0, floor2)
    if sigma2 <= 1e-24:
        return v_inf if c_inf <= 1e-20 else v
    f_stat = (c_inf - c_fin) / sigma2
    crit = (_f_ppf(1 - alpha, 1, dof) if dof > 0 and sigma2 > floor2
            else _chi2_ppf(1 - alpha, 1))
    return v_inf if f_stat < crit else v


def _spacing_fit(line_pts: Sequence[np.ndarray], sp_pts: Sequence[np.ndarray],
                 sp_pos: Sequence[np.ndarray], v0: np.ndarray, at_infinity: bool = False,
                 ) -> tuple[np.ndarray, float, int]:
    """Joint ML fit of a VP to line tracks and equally spaced tracks.

    A line track costs its squared orthogonal distances to the line through the VP
    (:func:`_track_costs`). An equally spaced track t with instance ordinals k has its
    points modelled as the images of equally spaced 3D points,
    ``x_k = dehom((a_t, 1) + k * lambda_t * v)`` (``a_t`` its first point, ``lambda_t``
    its image spacing scale), and costs its squared 2D residuals.

    Returns
    -------
    v : (3,) unit homogeneous VP (w = 0 when ``at_infinity``)
    cost : float, sum of squared residuals (coordinates of the points)
    dof : int, residual degrees of freedom
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    v0 = np.asarray(v0, float) / np.linalg.norm(v0)
    n_lt = len(line_pts)
    if n_lt:
        lph, lmask, lref = _padded_tracks(line_pts)
        n_line = int(lmask.sum())
    else:
        n_line = 0
    ts = len(sp_pts)
    kmax = max(len(q) for q in sp_pts)
    pp = np.zeros((ts, kmax, 2))
    kk = np.zeros((ts, kmax))
    mask = np.zeros((ts, kmax), bool)
    for i, (q, k) in enumerate(zip(sp_pts, sp_pos)):
        o = np.argsort(k, kind="stable")
        pp[i, :len(q)] = np.asarray(q, float)[o]
        kk[i, :len(q)] = np.asarray(k, float)[o] - float(np.min(k))
        mask[i, :len(q)] = True
    if at_infinity:
        d = v0[:2] if v0[2] == 0 and np.linalg.norm(v0[:2]) > 0 else (
            _fit_infinity(np.array([fit_line(q)[1] for q in list(line_pts) + list(sp_pts)]),
                          np.ones(len(line_pts) + ts))[:2])
        th0 = float(np.arctan2(d[1], d[0]))
        nv = 1

        def vec(x: np.ndarray) -> np.ndarray:
            return np.array([np.cos(th0 + x[0]), np.sin(th0 + x[0]), 0.0])
    else:
        _, _, vt = np.linalg.svd(v0.reshape(1, 3))
        u = vt[1:].T
        nv = 2

        def vec(x: np.ndarray) -> np.ndarray:
            v = v0 + u @ x[:2]
            return v / np.linalg.norm(v)

    vi = vec(np.zeros(nv))
    # initial a_t (first point) and lambda_t (linear least squares, see module notes)
    a0 = pp[:, 0, :]
    lam0 = np.zeros(ts)
    for i in range(ts):
        m = mask[i]
        x, k = pp[i, m], kk[i, m]
        g = k[:, None] * (x * vi[2] - vi[:2][None, :])  # lambda * g = a - x
        den = float((g ** 2).sum())
        lam0[i] = float((g * (a0[i][None, :] - x)).sum()) / den if den > 0 else 0.0
    x0 = np.concatenate([np.zeros(nv), np.c_[a0, lam0].ravel()])

    def resid(x: np.ndarray) -> np.ndarray:
        v = vec(x)
        par = x[nv:].reshape(ts, 3)
        h = (np.concatenate([par[:, :2], np.ones((ts, 1))], axis=1)[:, None, :]
             + (kk * par[:, 2:3])[:, :, None] * v[None, None, :])
        w = h[..., 2:3]
        w = np.where(np.abs(w) > 1e-9, w, 1e-9)
        r = np.where(mask[..., None], h[..., :2] / w - pp, 0.0)
        out = [r.reshape(-1)]
        if n_lt:
            out.insert(0, _track_residuals(v, lph, lmask, lref)[lmask])
        return np.concatenate(out)

    n_res = n_line + ts * kmax * 2
    sp = lil_matrix((n_res, len(x0)), dtype=int)
    sp[:, :nv] = 1
    for i in range(ts):
        r0 = n_line + i * kmax * 2
        sp[r0:r0 + kmax * 2, nv + 3 * i:nv + 3 * i + 3] = 1
    try:
        sol = least_squares(resid, x0, jac_sparsity=sp, method="trf", x_scale="jac",
                            xtol=1e-10, ftol=1e-10, max_nfev=60)
        x = sol.x if np.all(np.isfinite(sol.x)) else x0
    except (ValueError, np.linalg.LinAlgError):
        x = x0
    cost = float((resid(x) ** 2).sum())
    n_sp = int(mask.sum())
    dof = (n_line - n_lt) + (2 * n_sp - 3 * ts) - nv
    return vec(x), cost, dof


def spacing_refine_vp(points: Sequence[np.ndarray], positions: Sequence[np.ndarray | None],
                      v0: np.ndarray, alpha: float = 0.01, infinity_alpha: float = 0.01,
                      noise_floor: float = 0.0) -> np.ndarray | None:
    """ML VP from feature tracks where equally spaced rows also constrain the spacing.

    Along a row that is equally spaced in 3D, the images of one visual word are
    ``x_k = dehom(A + k * lambda * V)`` (A the first feature, V the VP): the image
    spacing shrinks towards the VP, which locates the VP *along* the row far better than
    the convergence of the row's short, nearly parallel feature tracks. Tracks with
    ``positions`` (instance ordinals, >= 3 points) get this model, the others the line
    model (:func:`ml_refine_vp`).

    The spacing model is accepted by a likelihood-ratio test against the line model of
    all tracks: ``(C_spacing - C_lines) / sigma^2`` below the ``1 - alpha`` quantile of
    chi^2(sum_t (K_t - 2)) (K_t - 2 constraints per spaced track; sigma^2 = the line
    model's residual variance, floored at ``noise_floor``). The accepted fit is then
    compared with the same model restricted to a VP at infinity (F-test of level
    ``infinity_alpha``, as :func:`ml_infinity_test`).

    Parameters
    ----------
    points : list of (K_t, 2) float
        Track points, normalised coordinates.
    positions : list of (K_t,) float or None
        Instance ordinals of the points of equally spaced tracks; None: line model.
    v0 : (3,) float
        Starting VP (the line-model ML VP).
    alpha, infinity_alpha : float
        Test levels.
    noise_floor : float
        Floor of the point noise sigma (units of ``points``).

    Returns
    -------
    (3,) float or None
        Unit homogeneous VP; None when the spacing model is rejected (or not
        applicable).
    """

    sp = [i for i, k in enumerate(positions) if k is not None and len(k) >= 3
          and len(np.unique(k)) == len(k)]
    if not sp or alpha <= 0:
        return None
    ln = [i for i in range(len(points)) if i not in set(sp)]
    line_pts = [points[i] for i in ln]
    sp_pts = [points[i] for i in sp]
    sp_pos = [positions[i] for i in sp]
    scat_all, n_all = _track_scatter(points)
    c_lines = float(_track_costs(np.asarray(v0, float) / np.linalg.norm(v0), scat_all).sum())
    dof_lines = n_all - len(points) - 2
    floor2 = noise_floor ** 2
    sigma2 = max(c_lines / dof_lines if dof_lines > 0 else 0.0, floor2, 1e-30)
    v, c_sp, dof = _spacing_fit(line_pts, sp_pts, sp_pos, v0)
    n_con = int(sum(len(points[i]) - 2 for i in sp))
    if (c_sp - c_lines) / sigma2 > _chi2_ppf(1 - alpha, n_con):
        return None
    if infinity_alpha > 0 and v[2] != 0 and dof > 0:
        v_inf, c_inf, _ = _spacing_fit(line_pts, sp_pts, sp_pos, v, at_infinity=True)
        s2 = max(c_sp / dof, floor2, 1e-30)
        crit = (_f_ppf(1 - infinity_alpha, 1, dof) if s2 > floor2
                else _chi2_ppf(1 - infinity_alpha, 1))
        if (c_inf - c_sp) / s2 < crit:
            v = v_inf
    return v / np.linalg.norm(v)


def ac_mask(d1: np.ndarray, d2: np.ndarray, ac_threshold_deg: float) -> np.ndarray:
    """Angular constraint: True where two line directions differ by at least the threshold.

    Parameters
    ----------
    d1, d2 : (P, 2) float
        Unit line directions (orientation does not matter).
    ac_threshold_deg : float
        Pairs closer to parallel than this (degrees) are refused (False).
    """
    d1 = np.asarray(d1, float).reshape(-1, 2)
    d2 = np.asarray(d2, float).reshape(-1, 2)
    s = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    s = s / np.maximum(np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1), 1e-300)
    return np.arcsin(np.clip(s, 0, 1)) >= np.radians(ac_threshold_deg)


def _maybe_infinity(v: np.ndarray, mids: np.ndarray, dirs: np.ndarray, w: np.ndarray,
                    alpha: float, noise_deg: float = 0.0) -> np.ndarray:
    """Replace v by the best point at infinity when an F-test cannot tell them apart.

    F = (RSS_inf - RSS_fin) / sigma^2 with sigma^2 = max(RSS_fin / (n - 2),
    sin^2(noise_deg) * mean weight); RSS = sum of w_i sin^2(angle_i). Snap when F is
    below the (1 - alpha) quantile of F(1, n - 2) (of chi^2(1) when sigma^2 is the floor).
    """
    if alpha <= 0 or v[2] == 0:
        return v
    n = len(dirs)
    v_inf = _fit_infinity(dirs, w)
    rss_fin = float((w * _sin_errors(v, mids, dirs) ** 2).sum())
    rss_inf = float((w * _sin_errors(v_inf, mids, dirs) ** 2).sum())
    floor = float(np.sin(np.radians(noise_deg)) ** 2 * w.mean())
    sigma2 = max(rss_fin / (n - 2) if n > 2 else 0.0, floor)
    if sigma2 <= 1e-24 * max(w.sum(), 1.0):
        # no noise at all: infinity only when the lines are parallel to rounding
        return v_inf if rss_inf <= 1e-20 * max(w.sum(), 1.0) else v

    f_stat = (rss_inf - rss_fin) / sigma2
    # estimated noise: F(1, n - 2); noise at its floor (treated as known): chi^2(1)
    crit = (_f_ppf(1 - alpha, 1, n - 2) if sigma2 > floor and n > 2
            else _chi2_ppf(1 - alpha, 1))
    return v_inf if f_stat < crit else v


def inside_image(vp: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Whether a homogeneous point lies inside ``[0, width] x [0, height]``."""
    v = np.asarray(vp, float)
    if abs(v[2]) <= INFINITY_EPS * np.linalg.norm(v):
        return False
    x, y = v[0] / v[2], v[1] / v[2]
    return bool(0 <= x <= image_size[0] and 0 <= y <= image_size[1])


# ----------------------------------------------------------------------------- RP VPD


RowTest = Callable[[np.ndarray | None, np.ndarray, list[np.ndarray]], list[bool] | None]
"""``row_test(feature_points (M, N', 2) | None, centres (N, 2), rows)``: per row, whether it
is equally spaced in 3D (None: no row is known to be), as
:func:`rescu.scene.analyse.equal_rows` decides with the translation-symmetry test."""


def rp_vanishing_point(bboxes: np.ndarray, feature_points: np.ndarray | None,
                       image_size: tuple[int, int], params: VPParams = VPParams(),
                       row_test: RowTest | None = None,
                       ) -> tuple[VanishingPoint | None, list[np.ndarray]]:
    """VP of one RP from its implicit lines.

    Parameters
    ----------
    bboxes : (N, 4) float
        Instance boxes ``[x, y, w, h]``, original pixels.
    feature_points : (M, N', 2) float or None
        Corresponding features, original pixels, NaN where missing (N' <= N).
    image_size : (int, int)
        ``(width, height)``, original pixels.
    params : VPParams
    row_test : callable or None
        Which rows are equally spaced in 3D (:data:`RowTest`; the scene step passes the
        translation-symmetry test, :func:`rescu.scene.analyse.equal_rows`): those rows
        also constrain the VP by their spacing (:func:`spacing_refine_vp`). None: no
        row is.

    Returns
    -------
    vp : VanishingPoint or None
        None when the instances form no row or there are too few lines.
    rows : list of int arrays
        The rows (instance indices in order) used, longest first.
    """
    b = np.asarray(bboxes, float)
    if b.ndim != 2 or b.shape[1] != 4:
        raise ValueError(f"bboxes must have shape (N, 4), got {b.shape}")
    if len(b) < 2:
        return None, []
    c, sz, rows = pattern_rows(b, feature_points, params)
    if not rows:
        return None, rows
    equal = row_test(feature_points, c, rows) if row_test is not None else None
    lines = pattern_lines(feature_points, c, rows, sz, params.max_line_residual,
                          params.precision_floor_px, equal)
    return ransac_vp(lines, image_size, params), rows



def joint_vanishing_point(line_sets: Sequence[Lines], vps: Sequence[VanishingPoint | None],
                          image_size: tuple[int, int], params: VPParams = VPParams(),
                          ) -> tuple[VanishingPoint | None, list[int]]:
    """VP of the first (dominant) pattern re-estimated on every pattern that shares it.

    Several RPs of a scene often recur along the same 3D direction (windows, sills and
    balconies of one facade), and the VP of a single row is poorly conditioned. Starting
    from the dominant pattern's inlier feature tracks, the other patterns are tried in
    the given order: pattern k is merged when the likelihood-ratio statistic
    ``(C_joint+k - C_joint - C_k) / sigma^2`` of a common VP (ML costs of
    :func:`ml_refine_vp`; sigma^2 = the pooled residual variance, floored at
    ``precision_floor_px``) is below the ``1 - joint_alpha`` quantile of chi^2(2).
    A pattern whose own VP is at infinity is never merged with one whose VP is finite
    (or vice versa). The merged VP gets the spacing model where merged rows are equally spaced
    (:func:`spacing_refine_vp`), else the point-level infinity test
    (:func:`ml_infinity_test`).

    Parameters
    ----------
    line_sets : list of Lines
        Implicit lines of each pattern (with ``points``), pixels; the first is the
        dominant pattern.
    vps : list of VanishingPoint or None
        Each pattern's own VP (None: the pattern is skipped).
    image_size : (int, int)
        ``(width, height)``, pixels.
    params : VPParams

    Returns
    -------
    vp : VanishingPoint or None
        The joint VP (the dominant one unchanged when nothing is merged or
        ``joint_alpha`` is 0); None when the dominant pattern has no VP.
    used : list of int
        Indices of the patterns whose tracks were used (the first is 0).
    """
    if len(line_sets) != len(vps):
        raise ValueError(f"line_sets and vps must have the same length, got "
                         f"{len(line_sets)} and {len(vps)}")
    if not vps or vps[0] is None:
        return None, []
    if params.joint_alpha <= 0 or len(vps) < 2:
        return vps[0], [0]

    t = _normaliser(image_size)
    sin_thr = np.sin(np.radians(params.inlier_angle_deg))
    floor2 = (params.precision_floor_px * t[0, 0]) ** 2
    sets: list[tuple[list[np.ndarray], list[np.ndarray | None], float, int] | None] = []
    for lines, vp in zip(line_sets, vps):
        if vp is None or lines.points is None or len(lines) < 2:
            sets.append(None)
            continue
        v = t @ np.asarray(vp.homogeneous, float)
        v = v / np.linalg.norm(v)
        mids = lines.midpoints * t[0, 0] + t[:2, 2]
        inl = [i for i in np.nonzero(_sin_errors(v, mids, lines.directions) < sin_thr)[0]
               if len(lines.points[i]) >= 2]
        pts = [lines.points[i] * t[0, 0] + t[:2, 2] for i in inl]
        pos = ([lines.positions[i] for i in inl] if lines.positions is not None
               else [None] * len(inl))
        if len(pts) < 2:
            sets.append(None)
            continue
        # each pattern's own minimum of the line-model cost (its free, finite ML VP)
        scat, n_pts = _track_scatter(pts)
        c_own = float(_track_costs(ml_refine_vp(pts, v), scat).sum())
        sets.append((pts, pos, c_own, n_pts - len(pts) - 2))
    if sets[0] is None:
        return vps[0], [0]
    v = t @ np.asarray(vps[0].homogeneous, float)
    v = v / np.linalg.norm(v)
    pts, pos, c_joint, dof = sets[0]
    used = [0]
    crit = _chi2_ppf(1 - params.joint_alpha, 2)
    for k in range(1, len(sets)):
        if sets[k] is None:
            continue
        pk, qk, ck, dk = sets[k]
        if (vps[k].homogeneous[2] == 0) != (vps[0].homogeneous[2] == 0):
            continue  # one pattern is seen frontally, the other not: no common VP
        cand = pts + pk
        v_c = ml_refine_vp(cand, v)
        scat, _ = _track_scatter(cand)
        c_c = float(_track_costs(v_c, scat).sum())
        sigma2 = max((c_joint + ck) / max(dof + dk, 1), floor2)
        if (c_c - c_joint - ck) / sigma2 < crit:
            pts, pos, v, c_joint, dof = cand, pos + qk, v_c, c_c, dof + dk + 2
            used.append(k)
    if len(used) == 1:
        return vps[0], used
    v_sp = None
    if params.spacing_alpha > 0 and any(k is not None and len(k) >= 3 for k in pos):
        v_sp = spacing_refine_vp(pts, pos, v, params.spacing_alpha, params.infinity_alpha,
                                 params.infinity_noise_px * t[0, 0])
    if v_sp is not None:
        v = v_sp
    elif v[2] != 0:
        v = ml_infinity_test(pts, v, params.infinity_alpha,
                             params.infinity_noise_px * t[0, 0])
    v_px = _canonical(np.linalg.solve(t, v))
    return VanishingPoint(v_px, inside_image(v_px, image_size), len(pts)), used


# ----------------------------------------------------------------------------- baseline
def lsd_segments(gray: np.ndarray, min_length: float = 0.0,
                 max_segments: int | None = None) -> np.ndarray:
    """LSD line segments of a grayscale (H, W) or RGB (H, W, 3) uint8 image.

    Returns (L, 4) float ``[x1, y1, x2, y2]`` pixels, at least ``min_length`` pixels long,
    the longest ``max_segments`` (ordered by decreasing length).
    """
    import cv2

    img = np.asarray(gray)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ValueError(f"gray must have shape (H, W) or (H, W, 3), got {img.shape}")
    img = np.ascontiguousarray(img, dtype=np.uint8)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    segs = lsd.detect(img)[0]
    if segs is None:
        return np.zeros((0, 4))
    s = segs.reshape(-1, 4).astype(float)
    length = np.linalg.norm(s[:, 2:] - s[:, :2], axis=1)
    order = np.lexsort((np.arange(len(s)), -length))
    s, length = s[order], length[order]
    s = s[length >= min_length]
    if max_segments is not None:
        s = s[:max_segments]
    return s


def line_vanishing_point(rgb: np.ndarray, params: VPParams = VPParams(),
                         scale_factor: float = 1.0) -> VanishingPoint | None:
    """Baseline dominant VP from explicit LSD line segments + RANSAC.

    Parameters
    ----------
    rgb : (H, W, 3) or (H, W) uint8
        The processed image (original * ``scale_factor``).
    params : VPParams
    scale_factor : float
        processed = original * scale_factor; the VP is returned in original pixels.

    Returns
    -------
    VanishingPoint or None
        Segments weighted by length; ``support`` = number of inlier segments.
    """
    if scale_factor <= 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    h, w = np.asarray(rgb).shape[:2]
    diag = float(np.hypot(w, h))
    segs = lsd_segments(rgb, params.lsd_min_length * diag, params.lsd_max_segments)
    vp = ransac_vp(Lines.from_segments(segs), (w, h), params)
    if vp is None:
        return None
    v = _canonical(np.diag([1.0, 1.0, scale_factor]) @ vp.homogeneous)
    orig = (round(w / scale_factor), round(h / scale_factor))
    return VanishingPoint(v, inside_image(v, orig), vp.support)


# ----------------------------------------------------------------------------- errors
def _is_inf(v: np.ndarray) -> bool:
    return abs(float(v[2])) <= INFINITY_EPS * float(np.linalg.norm(v))


def point_error(vp: np.ndarray, gt: np.ndarray) -> float:
    """Point-based error: pixel distance between two homogeneous VPs.

    ``inf`` when exactly one is at infinity; when both are at infinity, 0 if they are the
    same direction (to 1e-9 rad) else ``inf``.
    """
    a, b = np.asarray(vp, float), np.asarray(gt, float)
    if a.shape != (3,) or b.shape != (3,):
        raise ValueError(f"vp and gt must have shape (3,), got {a.shape} and {b.shape}")
    ia, ib = _is_inf(a), _is_inf(b)
    if ia and ib:
        da, db = a[:2] / np.linalg.norm(a[:2]), b[:2] / np.linalg.norm(b[:2])
        return 0.0 if abs(da[0] * db[1] - da[1] * db[0]) < 1e-9 else float("inf")
    if ia or ib:
        return float("inf")
    return float(np.hypot(a[0] / a[2] - b[0] / b[2], a[1] / a[2] - b[1] / b[2]))


def vp_direction(vp: np.ndarray, image_size: tuple[int, int], focal: float | None = None,
                 principal_point: Sequence[float] | None = None) -> np.ndarray:
    """Unit 3D direction ``(vp_x - x0, vp_y - y0, f)`` of a homogeneous VP.

    ``(x0, y0)`` is ``principal_point`` or the image centre; ``f`` is ``focal`` or
    ``(width + height) / 4``. A point at infinity ``(x, y, 0)`` has direction ``(x, y, 0)``.
    Computed homogeneously as ``(x - x0 w, y - y0 w, f w)``, so it is continuous at
    infinity.
    """
    v = np.asarray(vp, float)
    if v.shape != (3,):
        raise ValueError(f"vp must have shape (3,), got {v.shape}")
    w_, h_ = image_size
    x0, y0 = (w_ / 2.0, h_ / 2.0) if principal_point is None else principal_point
    f = (w_ + h_) / 4.0 if focal is None else float(focal)
    d = np.array([v[0] - x0 * v[2], v[1] - y0 * v[2], f * v[2]])
    return d / np.linalg.norm(d)


def vector_error(vp: np.ndarray, gt: np.ndarray, image_size: tuple[int, int],
                 focal: float | None = None,
                 principal_point: Sequence[float] | None = None) -> float:
    """Vector-based error: angle (degrees, in [0, 90]) between the VPs' 3D directions.

    Directions are undirected (a VP and its antipode are the same), so the angle is
    ``acos(|d1 . d2|)``. See :func:`vp_direction` for ``focal`` and ``principal_point``.
    """
    d1 = vp_direction(vp, image_size, focal, principal_point)
    d2 = vp_direction(gt, image_size, focal, principal_point)
    c = float(abs(d1 @ d2))
    # acos is ill-conditioned near 1: use atan2 of |cross| and |dot|
    s = float(np.linalg.norm(np.cross(d1, d2)))
    return float(np.degrees(np.arctan2(s, c)))


def closest_gt_error(vp: np.ndarray, gts: Sequence[np.ndarray], kind: str,
                     image_size: tuple[int, int], focal: float | None = None,
                     principal_point: Sequence[float] | None = None) -> float:
    """Error to the closest of several ground-truth VPs (``kind`` "vector" or "point").

    With several ground-truth VPs (York Urban has three per image, the synthetic set one
    per row direction) a detected VP is scored against the one it is closest to.
    ``inf`` (point) / ``nan`` (vector) when there is no ground truth.
    """
    if kind not in ("vector", "point"):
        raise ValueError(f"kind must be 'vector' or 'point', got {kind!r}")
    if not len(gts):
        return float("inf") if kind == "point" else float("nan")
    if kind == "point":
        return min(point_error(vp, g) for g in gts)
    return min(vector_error(vp, g, image_size, focal, principal_point) for g in gts)


def success_rate(errors: Sequence[float], thresholds: Sequence[float] | float) -> np.ndarray:
    """Fraction of errors <= each threshold (a missing VP counts as an infinite error).

    Parameters
    ----------
    errors : (n,) float
        Per-image errors; NaN or inf count as failures.
    thresholds : (T,) float or float

    Returns
    -------
    (T,) float (or a 0-d array for a scalar threshold); NaN when ``errors`` is empty.
    """
    e = np.asarray(errors, float).reshape(-1)
    t = np.asarray(thresholds, float)
    if len(e) == 0:
        return np.full(t.shape, np.nan)
    e = np.where(np.isnan(e), np.inf, e)
    return (e[None, :] <= t.reshape(-1, 1)).mean(axis=1).reshape(t.shape)


def paired_test(errors_a: Sequence[float], errors_b: Sequence[float]) -> float:
    """Two-sided Wilcoxon signed-rank p-value between two methods' per-image errors.

    Pairs where either error is NaN are left out; infinite errors (a missing VP) are
    replaced by a value above every finite error (the test uses ranks only). Returns 1.0
    when all the paired differences are zero or fewer than one pair remains.
    """
    from scipy.stats import wilcoxon

    a = np.asarray(errors_a, float).reshape(-1)
    b = np.asarray(errors_b, float).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"errors_a and errors_b must have the same length, "
                         f"got {a.shape} and {b.shape}")
    ok = ~(np.isnan(a) | np.isnan(b))
    a, b = a[ok], b[ok]
    fin = np.concatenate([a[np.isfinite(a)], b[np.isfinite(b)]])
    big = (float(np.abs(fin).max()) if len(fin) else 0.0) * 2 + 1.0
    a = np.where(np.isinf(a), np.sign(a) * big, a)
    b = np.where(np.isinf(b), np.sign(b) * big, b)
    d = a - b
    if len(d) == 0 or np.all(d == 0):
        return 1.0
    res = wilcoxon(a, b, zero_method="wilcox")
    p = float(res.pvalue)
    return p if np.isfinite(p) else 1.0
