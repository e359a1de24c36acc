"""Maximum-likelihood refinement of a VP on feature tracks, and the point-level tests.

A *track* is the features of one visual word along one row (the points an implicit line
was fitted to). :func:`ml_refine_vp` minimises the squared orthogonal distances of all
the track points to one line per track through the VP; :func:`ml_infinity_test` decides
between that VP and the best point at infinity (F-test on the points);
:func:`spacing_refine_vp` adds the spacing model of rows that are equally spaced in 3D
(likelihood-ratio test). Everything here works in normalised coordinates
(:func:`rescu.scene.vp.geometry._normaliser`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ...layout import fit_line
from .geometry import _chi2_ppf, _f_ppf, _fit_infinity


def _pencil(v: np.ndarray, scat: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The generalised eigenproblem of :func:`_track_costs`: the basis ``b`` (3, 2) of
    v's orthogonal complement, ``m = B^T S B`` (T, 2, 2), ``nn = B_xy^T B_xy`` (2, 2) and
    the smallest eigenvalue ``lam`` (T,) of each track (its cost)."""
    _, _, vt = np.linalg.svd(v.reshape(1, 3))
    b = vt[1:].T  # (3, 2)
    m = np.einsum("ia,tij,jb->tab", b, scat, b)
    nn = b[:2].T @ b[:2]
    qa = nn[0, 0] * nn[1, 1] - nn[0, 1] ** 2
    qb = -(m[:, 0, 0] * nn[1, 1] + m[:, 1, 1] * nn[0, 0] - 2 * m[:, 0, 1] * nn[0, 1])
    qc = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] ** 2
    disc = np.sqrt(np.maximum(qb ** 2 - 4 * qa * qc, 0.0))
    den = -qb + disc
    lam = np.where(den > 0, 2 * np.maximum(qc, 0.0) / np.where(den > 0, den, 1.0), 0.0)
    return b, m, nn, lam


def _track_costs(v: np.ndarray, scat: np.ndarray) -> np.ndarray:
    """Smallest sum of squared orthogonal distances of each track to a line through v.

    v : (3,) homogeneous point (finite or at infinity); scat : (T, 3, 3) sums of
    p~ p~^T over each track's points p~ = (x, y, 1). The line through v is
    l = B a with B a basis of v's orthogonal complement; the distance of p~ to l is
    l . p~ / |l_xy|, so the cost is the smallest generalised eigenvalue lambda of
    (B^T S B, B^T diag(1, 1, 0) B): a root of det(M - lambda N) = 0.
    """
    return _pencil(v, scat)[3]


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
    b, m, nn, lam = _pencil(v, np.einsum("tki,tkj->tij", ph, ph))
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

    Point-level test on the feature tracks (same cost as :func:`ml_refine_vp`, all points
    weighted equally): C = sum of squared orthogonal distances of the points to their
    track's line through the VP; F = (C_inf - C_fin) / sigma^2 with sigma^2 = max(C_fin /
    dof, noise_floor^2), dof = P - T - 2 (P points, T tracks: one angle per track and two VP
    coordinates). Snap when F is below the (1 - alpha) quantile of F(1, dof) (of chi^2(1)
    when sigma^2 is the floor). Unlike the line-level test
    (:func:`rescu.scene.vp.ransac._maybe_infinity`, dof = T - 2) it keeps the power of all
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
