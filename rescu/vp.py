"""Vanishing-point detection (VPD) from recurring patterns, a line baseline, and VP errors.

RP-based VPD (no explicit lines)
--------------------------------
When the instances of an RP recur along a line in 3D, the corresponding features of
one visual word across the instances lie on an *implicit line* in the image, and the
implicit lines of all visual words (and of all parallel rows of the RP) meet at the
vanishing point (VP) of the recurrence direction.

1. :func:`group_rows` orders the instances into collinear *rows* (greedy multi-line
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
from typing import Any, Sequence

import numpy as np

from .types import VanishingPoint
from .params import params_from_dict

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
    seed : int
        Seed of the random pair sampling.
    """

    ransac_iterations: int = 1000
    inlier_angle_deg: float = 1.5
    ac_threshold_deg: float = 2.0
    min_lines: int = 2
    infinity_alpha: float = 0.01
    infinity_noise_deg: float = 0.5
    row_tolerance: float = 0.25
    min_row_instances: int = 3
    max_line_residual: float = 0.15
    precision_floor_px: float = 1.0
    lsd_min_length: float = 0.025
    lsd_max_segments: int = 1500
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
    """

    midpoints: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    precision: np.ndarray | None = None

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
        return cls(np.concatenate([p.midpoints for p in parts]),
                   np.concatenate([p.directions for p in parts]),
                   np.concatenate([p.weights for p in parts]),
                   np.concatenate([p.precision for p in parts]))


def fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Total-least-squares line through points.

    Parameters
    ----------
    points : (P, 2) float, pixels, P >= 2

    Returns
    -------
    centroid : (2,) float, pixels
    direction : (2,) float, unit
    rms : float
        RMS orthogonal distance of the points to the line, pixels.
    """
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"points must have shape (P, 2) with P >= 2, got {p.shape}")
    c = p.mean(axis=0)
    q = p - c
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    d = vt[0]
    rms = float(s[1] / np.sqrt(len(p))) if len(s) > 1 else 0.0
    return c, d, rms


# ----------------------------------------------------------------------------- rows
def _segments_cross(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    """Whether segments p1-p2 and q1-q2 cross properly (touching does not count)."""
    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return d1 * d2 < 0 and d3 * d4 < 0


def group_rows(centres: np.ndarray, sizes: np.ndarray, row_tolerance: float = 0.25,
               min_row_instances: int = 3) -> list[np.ndarray]:
    """Split the instances of an RP into collinear rows, the longest rows first.

    Greedy multi-line search: every line through two remaining instance centres collects
    the centres within ``row_tolerance * sizes[k]`` of it; the line with most instances
    becomes a row (ties: spacing per instance within 1.3 x the smallest, which excludes
    grid diagonals, then the most horizontal line, then the lowest indices) and its instances are removed. A row may
    not cross an earlier row, so a grid gives all its rows or all its columns and no
    diagonals. A pattern of exactly two instances is one row.

    Parameters
    ----------
    centres : (N, 2) float
        Instance centres, pixels.
    sizes : (N,) float
        Instance size (smaller box side), pixels.
    row_tolerance : float
        Distance tolerance as a fraction of the instance size.
    min_row_instances : int
        Fewest instances in a row.

    Returns
    -------
    list of (K,) int arrays
        Instance indices of each row, ordered along the row (by projection onto the row
        direction, from left to right, or top to bottom for a vertical row).
    """
    c = np.asarray(centres, float)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"centres must have shape (N, 2), got {c.shape}")
    sz = np.asarray(sizes, float).reshape(-1)
    if sz.shape != (len(c),):
        raise ValueError(f"sizes must have shape ({len(c)},), got {sz.shape}")
    n = len(c)
    if n == 2:
        return [_order_along(c, np.array([0, 1]))] if np.any(c[0] != c[1]) else []
    remaining = np.arange(n)
    tol = row_tolerance * np.maximum(sz, 1e-9)
    rows: list[np.ndarray] = []
    segments: list[tuple[np.ndarray, np.ndarray]] = []
    while len(remaining) >= min_row_instances:
        best = _best_row(c, tol, sz, remaining, min_row_instances, segments)
        if best is None:
            break
        row = _order_along(c, best)
        rows.append(row)
        segments.append((c[row[0]], c[row[-1]]))
        remaining = np.setdiff1d(remaining, row)
    return rows


def _order_along(c: np.ndarray, idx: np.ndarray) -> np.ndarray:
    _, d, _ = fit_line(c[idx])
    if d[0] < -1e-12 or (abs(d[0]) <= 1e-12 and d[1] < 0):
        d = -d
    t = c[idx] @ d
    return np.asarray(idx)[np.lexsort((np.asarray(idx), t))]


def _best_row(c: np.ndarray, tol: np.ndarray, sz: np.ndarray, remaining: np.ndarray,
              min_k: int, segments: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    r = remaining
    ii, jj = np.triu_indices(len(r), k=1)
    a, b = c[r[ii]], c[r[jj]]
    d = b - a
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 0
    ii, jj, a, d, norm = ii[ok], jj[ok], a[ok], d[ok], norm[ok]
    if len(ii) == 0:
        return None
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / norm[:, None]
    dist = np.abs(np.einsum("pk,pnk->pn", nrm, c[r][None, :, :] - a[:, None, :]))
    inl = dist <= tol[r][None, :]
    counts = inl.sum(axis=1)
    order = np.argsort(-counts, kind="stable")
    med = float(np.median(sz[r])) if len(r) else 1.0
    cands: list[tuple[int, float, float, tuple[int, ...], np.ndarray]] = []
    for p in order:
        k = int(counts[p])
        if k < min_k or (cands and k < cands[0][0]):
            break
        idx = r[np.nonzero(inl[p])[0]]
        row = _order_along(c, idx)
        p1, p2 = c[row[0]], c[row[-1]]
        if any(_segments_cross(p1, p2, q1, q2) for q1, q2 in segments):
            continue
        span = float(np.linalg.norm(p2 - p1)) / (k - 1) / max(med, 1e-9)
        u = (p2 - p1) / max(np.linalg.norm(p2 - p1), 1e-12)
        cands.append((k, span, abs(float(u[0])), tuple(sorted(idx.tolist())), idx))
    if not cands:
        # the longest lines all cross earlier rows: try shorter ones
        for p in order:
            k = int(counts[p])
            if k < min_k:
                break
            idx = r[np.nonzero(inl[p])[0]]
            row = _order_along(c, idx)
            if not any(_segments_cross(c[row[0]], c[row[-1]], q1, q2) for q1, q2 in segments):
                return idx
        return None
    smin = min(x[1] for x in cands)
    # 1.3 < sqrt(2): a diagonal of a grid never survives, rows and columns of similar
    # spacing both do and the more horizontal one is taken
    cands = [x for x in cands if x[1] <= 1.3 * smin + 1e-12]
    cands.sort(key=lambda x: (-x[2], x[3]))
    return cands[0][4]


def checked_points(centres: np.ndarray, feature_points: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate instance centres (N, 2) and feature points (M, N', 2), pixels.

    Returns float copies; the feature points are padded with NaN columns to N instances
    (instances added by stage II have no features).
    """
    c = np.asarray(centres, float)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"centres must have shape (N, 2), got {c.shape}")
    fp = None
    if feature_points is not None:
        fp = np.asarray(feature_points, float)
        if fp.ndim != 3 or fp.shape[2] != 2:
            raise ValueError(f"feature_points must have shape (M, N, 2), got {fp.shape}")
        if fp.shape[1] < len(c):
            pad = np.full((fp.shape[0], len(c) - fp.shape[1], 2), np.nan)
            fp = np.concatenate([fp, pad], axis=1)
    return c, fp


def pattern_lines(feature_points: np.ndarray | None, centres: np.ndarray,
                  rows: Sequence[np.ndarray], sizes: np.ndarray | None = None,
                  max_line_residual: float = 0.15, precision_floor_px: float = 1.0) -> Lines:
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
        Instance indices of each row, from :func:`group_rows`.
    sizes : (N,) float or None
        Instance sizes, pixels (for the residual check; None: no check).
    max_line_residual : float
        Lines with RMS residual above this fraction of the median row instance size are
        dropped.
    precision_floor_px : float
        Noise floor (pixels) of the line precision weights of the refinement
        (:func:`_line_precision`); 0 gives all lines the same weight.

    Returns
    -------
    Lines
        A word needs a finite point in at least min(3, row length) instances of the row.
        A row without any feature line gives the line through its instance centres.
    """
    c, fp = checked_points(centres, feature_points)
    mids, dirs, prec = [], [], []
    for row in rows:
        row = np.asarray(row, int)
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
                got += 1
        if got == 0 and len(row) >= 2:
            cen, d, rms = fit_line(c[row])
            if rms <= max_line_residual * scale or len(row) == 2:
                mids.append(cen)
                dirs.append(d)
                prec.append(_line_precision(c[row], cen, d, rms, precision_floor_px))
    if not mids:
        return Lines.empty()
    p = np.array(prec)
    return Lines(np.array(mids), np.array(dirs), np.ones(len(mids)), p / p.mean())


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
    v = _maybe_infinity(v, mids[inl], dirs[inl], wf[inl], params.infinity_alpha,
                        params.infinity_noise_deg)
    v_px = np.linalg.solve(t, v)
    v_px = _canonical(v_px)
    return VanishingPoint(v_px, inside_image(v_px, image_size), int(inl.sum()))


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
    from scipy.stats import chi2
    from scipy.stats import f as f_dist

    f_stat = (rss_inf - rss_fin) / sigma2
    # estimated noise: F(1, n - 2); noise at its floor (treated as known): chi^2(1)
    crit = (f_dist.ppf(1 - alpha, 1, n - 2) if sigma2 > floor and n > 2
            else chi2.ppf(1 - alpha, 1))
    return v_inf if f_stat < crit else v


def inside_image(vp: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Whether a homogeneous point lies inside ``[0, width] x [0, height]``."""
    v = np.asarray(vp, float)
    if abs(v[2]) <= INFINITY_EPS * np.linalg.norm(v):
        return False
    x, y = v[0] / v[2], v[1] / v[2]
    return bool(0 <= x <= image_size[0] and 0 <= y <= image_size[1])


# ----------------------------------------------------------------------------- RP VPD
def instance_centres_sizes(bboxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 2) and sizes (smaller side, (N,)) of boxes (N, 4) ``[x, y, w, h]``."""
    b = np.asarray(bboxes, float).reshape(-1, 4)
    return b[:, :2] + b[:, 2:] / 2, np.minimum(b[:, 2], b[:, 3])


def rp_vanishing_point(bboxes: np.ndarray, feature_points: np.ndarray | None,
                       image_size: tuple[int, int], params: VPParams = VPParams(),
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
    c, sz = instance_centres_sizes(b)
    rows = group_rows(c, sz, params.row_tolerance, params.min_row_instances)
    if not rows:
        return None, rows
    lines = pattern_lines(feature_points, c, rows, sz, params.max_line_residual,
                          params.precision_floor_px)
    return ransac_vp(lines, image_size, params), rows


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
