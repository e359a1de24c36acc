"""Projective rows and lattices: the geometry of equally spaced instances, no image.

Instances equally spaced in 3D along a line project to positions along the image row
(a 1D projective map of the integer lattice, :func:`fit_projective_row`)::

    t(k) = (a k + b) / (c k + 1),     k = 0, 1, 2, ...

and two neighbouring rows of a grid to the cells (u, v), v = 0 / 1, of a homography
from integer cells to the image (:func:`lattice_pair_fit`). :mod:`rescu.scene.completion`
uses them to hypothesise the missing instances of rows and grids, which it then checks
on the image. Positions are pixels.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np


def fit_projective_row(k: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares 1D projective row ``t = (a k + b) / (c k + 1)``.

    Parameters
    ----------
    k : (K,) float
        Lattice indices (K >= 3).
    t : (K,) float
        Positions along the row, pixels.

    Returns
    -------
    abc : (3,) float
        ``(a, b, c)``.
    rms : float
        RMS residual of ``t``, pixels (inf when the model is singular at some k).
    """
    k = np.asarray(k, float).reshape(-1)
    t = np.asarray(t, float).reshape(-1)
    if k.shape != t.shape or len(k) < 3:
        raise ValueError(f"k and t must have the same shape (K,), K >= 3; got {k.shape}, "
                         f"{t.shape}")
    # a k + b - c k t = t  (linear in a, b, c)
    A = np.stack([k, np.ones_like(k), -k * t], axis=1)
    abc = np.linalg.lstsq(A, t, rcond=None)[0]
    den = abc[2] * k + 1
    if np.any(np.abs(den) < 1e-9):
        return abc, float("inf")
    return abc, float(np.sqrt(np.mean((row_model(abc, k) - t) ** 2)))


def row_model(abc: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Positions ``(a k + b) / (c k + 1)`` of lattice indices k (pixels).

    >>> row_model(np.array([10.0, 5.0, 0.0]), np.arange(4)).tolist()
    [5.0, 15.0, 25.0, 35.0]
    """
    a, b, c = abc
    k = np.asarray(k, float)
    return (a * k + b) / (c * k + 1)


def gap_hypotheses(n: int, max_gaps: int) -> list[np.ndarray]:
    """Lattice indices of n found instances with 1..max_gaps interior integers skipped.

    Returns
    -------
    list of (n,) int arrays
        ``k`` with ``k[0] = 0``, increasing; fewer gaps first, then lexicographic.

    Three instances with one lattice position missing between them:

    >>> [k.tolist() for k in gap_hypotheses(3, 1)]
    [[0, 2, 3], [0, 1, 3]]
    """
    out = []
    for g in range(1, max_gaps + 1):
        for combo in itertools.combinations_with_replacement(range(n - 1), g):
            steps = np.ones(n - 1, int)
            for j in combo:
                steps[j] += 1
            out.append(np.concatenate([[0], np.cumsum(steps)]))
    return out


def steps_ok(abc: np.ndarray, k_lo: int, k_hi: int, max_step_ratio: float) -> bool:
    """The row model is defined, increasing, and its image steps between lattice indices
    k_lo..k_hi are within a factor ``max_step_ratio`` of each other.

    >>> steps_ok(np.array([10.0, 5.0, 0.0]), 0, 3, 1.5)      # equal steps
    True
    >>> steps_ok(np.array([10.0, 5.0, 0.2]), 0, 5, 1.5)      # steps shrink 3 x
    False
    """
    ks = np.arange(k_lo, k_hi + 1, dtype=float)
    den = abc[2] * ks + 1
    if np.any(den <= 1e-9):
        return False
    st = np.diff(row_model(abc, ks))
    if np.any(st <= 0):
        return False
    return bool(st.max() / st.min() <= max_step_ratio)


def lattice_pair_fit(ca: np.ndarray, cb: np.ndarray, tol_a: np.ndarray, tol_b: np.ndarray,
                     max_step: int = 2, max_step_ratio: float = 1.5
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Projective lattice through two neighbouring rows of instance centres.

    Every choice of two consecutive instances in row A and two in row B hypothesises the
    homography ``H`` sending lattice points (0, 0), (ga, 0), (0, 1), (gb, 1) to them
    (``ga, gb`` in 1..``max_step``: an empty cell may lie between two found instances);
    an instance is an inlier when the image position of its nearest lattice point on its
    row (v = 0 for A, 1 for B) is within its tolerance. The hypothesis with most inliers
    (ties: fewer empty cells between the instances of each row, i.e. the coarsest
    lattice, then smaller RMS) is refitted by least squares on its inliers.

    Parameters
    ----------
    ca : (NA, 2) float
        Centres of row A ordered along the row, pixels (NA >= 2).
    cb : (NB, 2) float
        Centres of row B, the same direction, pixels (NB >= 2).
    tol_a, tol_b : (NA,), (NB,) float
        Inlier tolerances, pixels.
    max_step : int
        Largest lattice step between two consecutive found instances of a row.
    max_step_ratio : float
        Perspective limit: the image lengths of the lattice steps over the rectangle of
        both rows are within this factor of each other (a lattice whose rows differ
        more is a sheared mislabelling).

    Returns
    -------
    (H, ua, ub) or None
        ``H`` (3, 3) lattice -> pixels; ``ua`` (NA,), ``ub`` (NB,) int lattice columns of
        the instances, ``INT_MIN`` for outliers. None when no hypothesis has at least two
        inliers in each row, five inliers in all (four points fit any lattice exactly)
        and three quarters of all instances as inliers.
    """
    ca, cb = np.asarray(ca, float), np.asarray(cb, float)
    na, nb = len(ca), len(cb)
    if na < 2 or nb < 2:
        return None
    best = None
    for ga, gb in itertools.product(range(1, max_step + 1), repeat=2):
        src = np.array([[0, 0], [ga, 0], [0, 1], [gb, 1]], np.float32)
        for k in range(na - 1):
            for m in range(nb - 1):
                dst = np.array([ca[k], ca[k + 1], cb[m], cb[m + 1]], np.float32)
                Hm = cv2.getPerspectiveTransform(src, dst)
                got = lattice_labels(Hm, ca, cb, tol_a, tol_b, max_step_ratio)
                if got is not None and (best is None or got[0] > best[0]):
                    best = got
    if best is None:
        return None
    _, Hm, ua, ub = best
    ok_a, ok_b = ua != OFF_LATTICE, ub != OFF_LATTICE
    if ok_a.sum() + ok_b.sum() > 4:  # refit on all inliers (overdetermined)
        lat = np.concatenate([np.stack([ua[ok_a], np.zeros(ok_a.sum())], 1),
                              np.stack([ub[ok_b], np.ones(ok_b.sum())], 1)]).astype(np.float32)
        img = np.concatenate([ca[ok_a], cb[ok_b]]).astype(np.float32)
        H2, _ = cv2.findHomography(lat, img, 0)
        if H2 is not None:
            got = lattice_labels(H2, ca, cb, tol_a, tol_b, max_step_ratio)
            if got is not None and got[0] >= best[0]:
                _, Hm, ua, ub = got
    return Hm, ua, ub


OFF_LATTICE = np.iinfo(np.int64).min
"""The column label of an instance that lies on no cell of the fitted lattice."""


def lattice_map(Hm: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Lattice points (P, 2) -> pixels (P, 2); NaN where behind the horizon (w <= 0).

    >>> H = np.array([[20.0, 0, 5], [0, 30, 7], [0, 0, 1]])
    >>> lattice_map(H, np.array([[0, 0], [1, 2]])).tolist()
    [[5.0, 7.0], [25.0, 67.0]]
    """
    q = np.c_[np.asarray(uv, float), np.ones(len(uv))] @ np.asarray(Hm, float).T
    w = q[:, 2:]
    return np.where(w > 1e-9, q[:, :2] / np.where(w > 1e-9, w, 1.0), np.nan)


def lattice_labels(Hm: np.ndarray, ca: np.ndarray, cb: np.ndarray, tol_a: np.ndarray,
                    tol_b: np.ndarray, max_step_ratio: float
                    ) -> tuple[tuple[int, int, float], np.ndarray, np.ndarray, np.ndarray] | None:
    """((inliers, -empty cells, -rms), H, ua, ub) of one lattice hypothesis, or None
    when invalid."""
    try:
        Hi = np.linalg.inv(np.asarray(Hm, float))
    except np.linalg.LinAlgError:
        return None
    out = []
    err2 = []
    for c, v, tol in ((ca, 0.0, tol_a), (cb, 1.0, tol_b)):
        uv = lattice_map(Hi, c)
        if not np.all(np.isfinite(uv)):
            return None
        u = np.round(uv[:, 0])
        pred = lattice_map(Hm, np.c_[u, np.full(len(u), v)])
        e = np.linalg.norm(pred - c, axis=1)
        ok = np.isfinite(e) & (e <= tol)
        lab = np.where(ok, u, 0).astype(np.int64)
        lab[~ok] = OFF_LATTICE
        if ok.sum() < 2 or len(set(lab[ok].tolist())) < ok.sum():  # two on one cell
            return None
        out.append(lab)
        err2.extend((e[ok] ** 2).tolist())
    n_in = int(sum((lab != OFF_LATTICE).sum() for lab in out))
    if n_in < max(5, 0.75 * (len(ca) + len(cb))):  # 4 points fit any lattice exactly
        return None
    # perspective limit: the steps over the lattice rectangle of both rows are within a
    # factor max_step_ratio of each other (as for one row: steps_ok)
    lo = int(min(lab[lab != OFF_LATTICE].min() for lab in out))
    hi = int(max(lab[lab != OFF_LATTICE].max() for lab in out))
    st = np.array([[lattice_step(Hm, u, v) for u in range(lo, hi + 1)] for v in (0.0, 1.0)])
    if not np.all(np.isfinite(st)) or np.any(st <= 0) or st.max() > max_step_ratio * st.min():
        return None
    on = [lab[lab != OFF_LATTICE] for lab in out]
    empty = sum(int(v.max() - v.min() + 1 - len(v)) for v in on)
    return (n_in, -empty, -float(np.sqrt(np.mean(err2)))), Hm, out[0], out[1]


def grid_missing_cells(ua: np.ndarray, ub: np.ndarray, max_missing: int
                       ) -> list[tuple[int, int]]:
    """Empty cells of the lattice rectangle spanned by two rows' columns.

    The lattice of two rows is known up to a shift ``s`` of row B's columns against row
    A's (a sheared labelling is an equally good lattice). For each shift with at least
    two shared columns the rectangle spanned by both rows has empty cells; the shifts
    with fewest empty cells (the rows most aligned, as in a rectangular grid) are kept,
    and the union of their empty cells is returned (each is verified on the image
    afterwards, so a wrong shift only costs a rejected candidate).

    Parameters
    ----------
    ua, ub : int arrays
        Lattice columns of the inlier instances of row A (v = 0) and row B (v = 1).
    max_missing : int
        Shifts with more empty cells than this are ignored.

    Returns
    -------
    list of (u, v)
        Empty cells in the lattice of ``ua``/``ub`` (v = 0 row A, 1 row B), sorted.
    """
    A, B = set(int(x) for x in ua), set(int(x) for x in ub)
    if len(A) < 2 or len(B) < 2:
        return []
    best: tuple[int, set[tuple[int, int]]] | None = None
    for s in range(min(A) - max(B), max(A) - min(B) + 1):
        Bs = {b + s for b in B}
        if len(A & Bs) < 2:
            continue
        lo, hi = min(A | Bs), max(A | Bs)
        cells = {(u, 0) for u in range(lo, hi + 1) if u not in A}
        cells |= {(u - s, 1) for u in range(lo, hi + 1) if u not in Bs}
        if not cells:
            return []  # a complete rectangle under some alignment: nothing to fill
        if len(cells) > max_missing:
            continue
        if best is None or len(cells) < best[0]:
            best = (len(cells), set(cells))
        elif len(cells) == best[0]:
            best[1].update(cells)
    return sorted(best[1]) if best else []


def lattice_step(Hm: np.ndarray, u: float, v: float) -> float:
    """Image length (pixels) of one lattice step along the row at column u of row v.

    >>> lattice_step(np.array([[20.0, 0, 5], [0, 30, 7], [0, 0, 1]]), 0, 0)
    20.0
    """
    a, b = lattice_map(Hm, np.array([[u - 0.5, v], [u + 0.5, v]], float))
    return float(np.linalg.norm(b - a))


def cell_wh(Hm: np.ndarray, wh_step: tuple[np.ndarray, float], u: float, v: float
             ) -> np.ndarray:
    """Box (w, h) of cell (u, v), pixels: the row's median box scaled by the lattice step
    there relative to the row's median step."""
    wh, step = wh_step
    return wh * (lattice_step(Hm, u, v) / step)
