"""The RP-based VP estimator: the VP of one recurring pattern and the image's joint VP.

:func:`rp_vanishing_point` groups the instances into rows (:func:`rescu.layout.pattern_rows`),
fits their implicit lines (:func:`rescu.scene.vp.lines.pattern_lines`) and runs
:func:`rescu.scene.vp.ransac.ransac_vp`; which rows are equally spaced in 3D (for the
spacing model) is asked of a :data:`RowTest` the caller passes (the scene step passes
the translation-symmetry test), so this module does not import the symmetry test.
:func:`joint_vanishing_point` re-estimates a VP on the tracks of several patterns that
share it; :func:`union_vanishing_point` finds the VP that the rows of all patterns
together point to (the scene step's image VP, when every pattern with a VP accepts it).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ...layout import pattern_rows
from ...types import VanishingPoint
from .geometry import _canonical, _chi2_ppf, _normaliser, _sin_errors, inside_image
from .lines import Lines, pattern_lines
from .params import VPParams
from .ransac import ransac_vp
from .refine import _track_costs, _track_scatter, ml_infinity_test, ml_refine_vp, spacing_refine_vp


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
        translation-symmetry test, :func:`rescu.scene.analyse.equal_rows`): those rows also
        constrain the VP by their spacing (:func:`rescu.scene.vp.refine.spacing_refine_vp`).
        None: no row is.

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
    :func:`rescu.scene.vp.refine.ml_refine_vp`; sigma^2 = the pooled residual variance, floored at
    ``precision_floor_px``) is below the ``1 - joint_alpha`` quantile of chi^2(2).
    A pattern whose own VP is at infinity is never merged with one whose VP is finite
    (or vice versa). The merged VP gets the spacing model where merged rows are equally spaced
    (:func:`rescu.scene.vp.refine.spacing_refine_vp`), else the point-level infinity test
    (:func:`rescu.scene.vp.refine.ml_infinity_test`).

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


def union_vanishing_point(line_sets: Sequence[Lines], vps: Sequence[VanishingPoint | None],
                          image_size: tuple[int, int], params: VPParams = VPParams(),
                          weights: Sequence[np.ndarray] | None = None,
                          ) -> tuple[VanishingPoint | None, int | None]:
    """The VP that the rows of all patterns together point to, checked against their own VPs.

    All patterns' implicit lines vote in one :func:`rescu.scene.vp.ransac.ransac_vp`, each
    line weighted by the length of its feature track (the number of instances it
    follows), so a VP that several patterns share, each with too few lines for a VP of its
    own, is found as well. The union can mix the rows of patterns that point to different
    but nearby VPs (two facades, nearly parallel rows); so every pattern that has a VP of
    its own and at least two inlier tracks must accept the union VP: the likelihood-ratio
    statistic ``(C(v_union) - C(v_own)) / sigma^2`` of its inlier tracks (ML costs of
    :func:`rescu.scene.vp.refine.ml_refine_vp`, ``v_own`` the free ML VP started from its
    own VP, ``sigma^2`` its residual variance floored at ``precision_floor_px``) must stay
    below the ``1 - joint_alpha`` quantile of chi^2(2).

    Parameters
    ----------
    line_sets : list of Lines
        Implicit lines of each pattern (with ``points``), pixels; may be empty.
    vps : list of VanishingPoint or None
        Each pattern's own VP (None: the pattern has none and is not asked).
    image_size : (int, int)
        ``(width, height)``, pixels.
    params : VPParams
    weights : list of (L_k,) float arrays or None
        Each line's vote instead of its track length (a study of the weighting).

    Returns
    -------
    vp : VanishingPoint or None
        The union VP (``support``: its inlier lines); None when there are too few lines
        or a pattern refuses it.
    refused : int or None
        The index of the first pattern that refused the union VP, else None.
    """
    if len(line_sets) != len(vps) or (weights is not None and len(weights) != len(vps)):
        raise ValueError(f"line_sets, vps (and weights) must have the same length, got "
                         f"{len(line_sets)}, {len(vps)}"
                         + ("" if weights is None else f" and {len(weights)}"))
    parts, owner = [], []
    for k, lines in enumerate(line_sets):
        if len(lines) == 0 or lines.points is None:
            continue
        vote = (np.array([float(len(q)) for q in lines.points]) if weights is None
                else np.asarray(weights[k], float).reshape(-1))
        if vote.shape != (len(lines),):
            raise ValueError(f"weights[{k}] must hold one vote per line ({len(lines)}), "
                             f"got {vote.size}")
        parts.append(Lines(lines.midpoints, lines.directions, vote, lines.precision,
                           lines.points, lines.positions))
        owner += [k] * len(lines)
    if not parts:
        return None, None
    union = Lines.concat(parts)
    vp = ransac_vp(union, image_size, params)
    if vp is None:
        return None, None
    t = _normaliser(image_size)
    v = t @ np.asarray(vp.homogeneous, float)
    v = v / np.linalg.norm(v)
    mids = union.midpoints * t[0, 0] + t[:2, 2]
    inl = _sin_errors(v, mids, union.directions) < np.sin(np.radians(params.inlier_angle_deg))
    own = np.asarray(owner)
    crit = _chi2_ppf(1 - params.joint_alpha, 2) if params.joint_alpha > 0 else np.inf
    floor2 = (params.precision_floor_px * t[0, 0]) ** 2
    assert union.points is not None
    for k in dict.fromkeys(own[inl].tolist()):
        if vps[k] is None:
            continue
        pts = [union.points[i] * t[0, 0] + t[:2, 2] for i in np.nonzero(inl & (own == k))[0]
               if len(union.points[i]) >= 2]
        if len(pts) < 2:
            continue
        scat, n_pts = _track_scatter(pts)
        vo = t @ np.asarray(vps[k].homogeneous, float)
        c_own = float(_track_costs(ml_refine_vp(pts, vo / np.linalg.norm(vo)), scat).sum())
        c_union = float(_track_costs(v, scat).sum())
        sigma2 = max(c_own / max(n_pts - len(pts) - 2, 1), floor2)
        if (c_union - c_own) / sigma2 >= crit:
            return None, int(k)
    return vp, None
