"""RANSAC over line pairs with the angular constraint: :func:`ransac_vp`.

Hypotheses are the intersections of line pairs that pass the angular constraint and the
points at infinity along the lines; the best-supported one is refined by iteratively
reweighted least squares, then (where the lines carry their points) by the
maximum-likelihood fit of :mod:`rescu.scene.vp.refine`, and snapped to infinity when a
test cannot tell it from a point at infinity (:func:`_maybe_infinity` on the lines,
:func:`rescu.scene.vp.refine.ml_infinity_test` on the points).
"""

from __future__ import annotations

import numpy as np

from ...types import VanishingPoint
from .geometry import (_canonical, _chi2_ppf, _f_ppf, _fit_infinity, _fit_vp, _normaliser,
                       _sin_errors, ac_mask, inside_image)
from .lines import Lines
from .params import VPParams
from .refine import ml_infinity_test, ml_refine_vp, spacing_refine_vp


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
