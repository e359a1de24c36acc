"""3D translation symmetry (TS) of a recurring pattern via the cross ratio; rectification.

Cross ratio
-----------
For four collinear image points A, B, C, D (the corresponding features of four
consecutive instances of a row)::

    cr = (AC * BD) / (BC * AD)

is invariant under any projective map of the line, and equals 4/3 when AB = BC = CD in
3D (equally spaced instances). Distances are signed positions along the points' line
(the direction from A to D), so the measure is exact for collinear points and a
least-squares projection for noisy ones.

Test
----
:func:`translation_symmetry` collects the cross ratios of every 4-tuple of consecutive
instances of every row with at least ``min_instances`` instances, for every visual word
with a feature in all four (the instance centres when a 4-tuple has no such word), and
declares a *potential* TS when ``|cr_med - 4/3| <= threshold`` (t = 0.06 in the
paper). ``cr_med`` is the robust (median) cross ratio taken as the cross ratio at the
median of the deviations ``|cr - 4/3|`` (upper median for an even count): TS then needs
at least half of the 4-tuples within t. (The plain median of the cross ratios accepts
rows whose 4-tuples straddle 4/3, e.g. 1.16 and 1.64 -> 1.40: 17 % false positives on
unequal synthetic rows against 0 % for this rule.) The order of a row does not matter (``cr(A, B, C, D) = cr(D, C, B, A)``).

Rectification
-------------
:func:`vp_rectifying_homography` sends the RP's VP to infinity with
``H = [[1, 0, 0], [0, 1, 0], l]``, ``l`` being the line through the VP perpendicular to the
direction from the RP centre to the VP, scaled so that the centre is fixed (``l . c = 1``).
Along every line through the VP the map becomes affine, so equal 3D spacing along the
rows becomes equal image spacing, and the rows become parallel. (A full affine
rectification of the plane needs a second VP, which one RP direction does not give.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..layout import checked_points
from ..params import config_section, params_from_dict
from ..types import TranslationSymmetry

CR_EQUAL_SPACING = 4.0 / 3.0  # cross ratio of 4 equally spaced collinear points


@dataclass(frozen=True)
@config_section("scene", "symmetry")
class SymmetryParams:
    """Parameters of the translation-symmetry test.

    Attributes
    ----------
    threshold : float
        t: potential TS when ``|cr - 4/3| <= t``.
    min_instances : int
        Fewest instances in a row for the test (at least 4).
    """

    threshold: float
    min_instances: int

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "SymmetryParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


def cross_ratio(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Cross ratio ``(AC * BD) / (BC * AD)`` of collinear points.

    Parameters
    ----------
    a, b, c, d : (..., 2) float
        Points in pixels, in order along their line (batched over leading axes).

    Returns
    -------
    (...) float
        The cross ratio (4/3 for equally spaced points); NaN where A = D or B = C.
    """
    pts = [np.asarray(p, float) for p in (a, b, c, d)]
    shape = pts[0].shape
    if shape[-1:] != (2,) or any(p.shape != shape for p in pts):
        raise ValueError("a, b, c, d must all have the same shape (..., 2), got "
                         f"{[p.shape for p in pts]}")
    a, b, c, d = pts
    ad = d - a
    n = np.linalg.norm(ad, axis=-1, keepdims=True)
    u = ad / np.where(n > 0, n, 1.0)
    # signed positions along the line A -> D
    ta = np.zeros(shape[:-1])
    tb = ((b - a) * u).sum(-1)
    tc = ((c - a) * u).sum(-1)
    td = n[..., 0]
    num = (tc - ta) * (td - tb)
    den = (tc - tb) * (td - ta)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(np.abs(den) > 0, num / np.where(np.abs(den) > 0, den, 1.0), np.nan)
    return out


def row_cross_ratios(points: np.ndarray) -> np.ndarray:
    """Cross ratios of all 4-tuples of consecutive points of a row.

    Parameters
    ----------
    points : (K, 2) float
        Points in order along the row, pixels.

    Returns
    -------
    (max(K - 3, 0),) float
    """
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must have shape (K, 2), got {p.shape}")
    if len(p) < 4:
        return np.zeros((0,))
    return cross_ratio(p[:-3], p[1:-2], p[2:-1], p[3:])


def translation_symmetry(feature_points: np.ndarray | None, centres: np.ndarray,
                         rows: Sequence[np.ndarray],
                         params: SymmetryParams = SymmetryParams(),
                         ) -> TranslationSymmetry | None:
    """Potential 3D translation symmetry of an RP from its rows.

    Parameters
    ----------
    feature_points : (M, N', 2) float or None
        Corresponding features, pixels, NaN where missing; column n is instance n
        (N' <= N; the later instances have no features).
    centres : (N, 2) float
        Instance centres, pixels.
    rows : list of int arrays
        Instance indices of each row in order along the row (see
        :func:`rescu.layout.group_rows`).
    params : SymmetryParams

    Returns
    -------
    TranslationSymmetry or None
        ``cross_ratio`` = the robust median (see module docstring) over all 4-tuples,
        ``n_tuples`` their number; None when
        no row has ``min_instances`` instances.
    """
    c, fp = checked_points(centres, feature_points)
    crs: list[np.ndarray] = []
    any_row = False
    for row in rows:
        row = np.asarray(row, int)
        if len(row) < params.min_instances:
            continue
        any_row = True
        for s in range(len(row) - 3):
            q = row[s:s + 4]
            got = False
            if fp is not None:
                pts = fp[:, q, :]  # (M, 4, 2)
                ok = np.all(np.isfinite(pts), axis=(1, 2))
                if ok.any():
                    p = pts[ok]
                    cr = cross_ratio(p[:, 0], p[:, 1], p[:, 2], p[:, 3])
                    cr = cr[np.isfinite(cr)]
                    if len(cr):
                        crs.append(cr)
                        got = True
            if not got:
                cr = cross_ratio(c[q[0]], c[q[1]], c[q[2]], c[q[3]])
                if np.isfinite(cr):
                    crs.append(np.atleast_1d(cr))
    if not any_row:
        return None
    allc = np.concatenate(crs) if crs else np.zeros((0,))
    if len(allc) == 0:
        return None
    # robust statistic: the cross ratio whose deviation from 4/3 is the median deviation
    # (the upper median for an even count), so TS needs at least half of the 4-tuples
    # within t; a plain median of the cross ratios would accept a row whose tuples
    # straddle 4/3 (e.g. 1.16 and 1.64 -> 1.40).
    dev = np.abs(allc - CR_EQUAL_SPACING)
    order = np.lexsort((allc, dev))
    cr_med = float(allc[order[len(allc) // 2]])
    return TranslationSymmetry(bool(abs(cr_med - CR_EQUAL_SPACING) <= params.threshold),
                               cr_med, int(len(allc)))


# ----------------------------------------------------------------------------- rectify
def vp_rectifying_homography(vp: np.ndarray, centre: Sequence[float]) -> np.ndarray:
    """Homography sending a VP to infinity and keeping ``centre`` fixed.

    Parameters
    ----------
    vp : (3,) float
        Homogeneous VP, pixels.
    centre : (2,) float
        Centre of the RP region, pixels (must not be the VP).

    Returns
    -------
    (3, 3) float
        ``H = [[1, 0, 0], [0, 1, 0], l]`` with ``l`` the line through the VP perpendicular
        to the direction centre -> VP, ``l . (centre, 1) = 1``; the identity when the VP
        is already at infinity. ``H @ vp`` has ``w = 0``.
    """
    v = np.asarray(vp, float)
    if v.shape != (3,):
        raise ValueError(f"vp must have shape (3,), got {v.shape}")
    c = np.asarray(centre, float)
    if c.shape != (2,):
        raise ValueError(f"centre must have shape (2,), got {c.shape}")
    v = v / np.linalg.norm(v)
    if abs(v[2]) <= 1e-12:
        return np.eye(3)
    p = v[:2] / v[2]
    dvec = p - c
    dist2 = float(dvec @ dvec)
    if dist2 <= 1e-12:
        raise ValueError("the VP coincides with the region centre: no rectification")
    # line through p with normal dvec: dvec . x - dvec . p = 0, scaled so l . c = 1
    l_ = np.array([dvec[0], dvec[1], -float(dvec @ p)])
    l_ = l_ / float(l_[:2] @ c + l_[2])
    h = np.eye(3)
    h[2] = l_
    return h
