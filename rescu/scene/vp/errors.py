"""The paper's two VP errors and the success rate over images.

:func:`point_error` (pixel distance of two homogeneous VPs), :func:`vector_error` (angle
between their back-projected 3D directions, :func:`vp_direction`),
:func:`closest_gt_error` (with several ground-truth VPs, the error to the closest one)
and :func:`success_rate` (share of errors within thresholds).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .geometry import INFINITY_EPS


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
