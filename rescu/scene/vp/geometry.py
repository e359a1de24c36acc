"""Homogeneous-point geometry shared by the VP estimators.

The normalisation of pixel coordinates (:func:`_normaliser`: image centre at 0,
(W + H) / 2 pixels to 1), the sine of the angle between a line and the direction to a
VP (:func:`_sin_errors`), the least-squares VP of lines (:func:`_fit_vp`,
:func:`_fit_infinity`), the sign convention of a VP (:func:`_canonical`), the angular
constraint (:func:`ac_mask`), :func:`inside_image`, the chi-squared and F quantiles
of the infinity tests (:func:`_chi2_ppf`, :func:`_f_ppf`), and the chi-squared survival
function of the claims' parallelism test (:func:`_chi2_sf`). A VP is a homogeneous
3-vector, ``w = 0`` for a point at infinity.
"""

from __future__ import annotations

import numpy as np


# |w| of a unit-norm homogeneous pixel point below which it is "at infinity" for the
# error measures (|w| = 1e-12 is a point about 1e12 pixels away).
INFINITY_EPS = 1e-12


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


def inside_image(vp: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Whether a homogeneous point lies inside ``[0, width] x [0, height]``."""
    v = np.asarray(vp, float)
    if abs(v[2]) <= INFINITY_EPS * np.linalg.norm(v):
        return False
    x, y = v[0] / v[2], v[1] / v[2]
    return bool(0 <= x <= image_size[0] and 0 <= y <= image_size[1])


def _chi2_ppf(q: float, df: float) -> float:
    """Quantile ``q`` of the chi-squared distribution with ``df`` degrees of freedom.

    What ``scipy.stats.chi2.ppf`` computes for 0 < q < 1, from ``scipy.special`` (whose
    import costs half of ``scipy.stats``'s, paid by every scene job).
    """
    from scipy.special import gammaincinv

    return float(2 * gammaincinv(df / 2, q))


def _chi2_sf(x: float, df: int) -> float:
    """Survival function of the chi-squared distribution with ``df`` degrees of freedom
    at ``x`` >= 0: what ``scipy.stats.chi2.sf`` computes (``scipy.special.chdtrc``, the
    same function), NaN for ``df`` < 1 as there, without ``scipy.stats``' import."""
    from scipy.special import chdtrc

    if df < 1:
        return float("nan")
    return float(chdtrc(df, max(float(x), 0.0)))


def _f_ppf(q: float, dfn: float, dfd: float) -> float:
    """Quantile ``q`` of Fisher's F(dfn, dfd), as ``scipy.stats.f.ppf`` for 0 < q < 1."""
    from scipy.special import fdtri

    return float(fdtri(dfn, dfd, q))
