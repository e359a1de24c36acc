"""Row geometry of a recurring pattern: where its instances are and which lie in rows.

Shared by stage I (duplicate instances located by their features), the VP estimator,
the translation-symmetry test, row completion and the scene step, so it lives below all
of them and imports nothing of rescu:

* :func:`instance_centres_sizes`: box centres and sizes;
* :func:`registered_centres`: instance positions registered by their corresponding
  features (a partial instance has a shifted box centre);
* :func:`duplicate_instances`: instances that duplicate another one;
* :func:`group_rows`: the instances split into collinear rows (greedy multi-line search,
  the longest rows first, no row crossing an earlier one);
* :func:`pattern_rows`: the three above in the order the VP estimator and the scene step
  use them, driven by any object with the :class:`RowParams` attributes (e.g.
  :class:`rescu.scene.vp.params.VPParams`);
* :func:`fit_line` (total least squares) and :func:`checked_points` (shape checks of
  centres and feature points).

All coordinates are pixels: centres ``(N, 2)``, sizes ``(N,)`` (the smaller box side),
feature points ``(M, N', 2)`` (visual word m of instance n, NaN where missing).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class RowParams(Protocol):
    """What :func:`pattern_rows` reads of its parameters (``VPParams`` has all three).

    Attributes
    ----------
    register_centres : bool
        Locate instances by their features (:func:`registered_centres`) and leave
        duplicate instances out of the rows.
    row_tolerance : float
        An instance centre belongs to a row within this fraction of its size.
    min_row_instances : int
        Fewest instances in a row.
    """

    register_centres: bool
    row_tolerance: float
    min_row_instances: int


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

    >>> c, d, rms = fit_line(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]]))
    >>> c.tolist(), np.abs(d).tolist(), round(rms, 6)
    ([10.0, 0.0], [1.0, 0.0], 0.0)
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

    A 3 x 2 grid of 10-px instances gives its two rows, no diagonal:

    >>> centres = np.array([[10, 10], [30, 10], [50, 10], [10, 40], [30, 40], [50, 40]], float)
    >>> [r.tolist() for r in group_rows(centres, np.full(6, 10.0))]
    [[0, 1, 2], [3, 4, 5]]
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


def instance_centres_sizes(bboxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 2) and sizes (smaller side, (N,)) of boxes (N, 4) ``[x, y, w, h]``.

    >>> c, s = instance_centres_sizes(np.array([[0, 0, 20, 10], [30, 0, 10, 10]]))
    >>> c.tolist(), s.tolist()
    ([[10.0, 5.0], [35.0, 5.0]], [10.0, 10.0])
    """
    b = np.asarray(bboxes, float).reshape(-1, 4)
    return b[:, :2] + b[:, 2:] / 2, np.minimum(b[:, 2], b[:, 3])


def registered_centres(centres: np.ndarray, feature_points: np.ndarray | None,
                       min_words: int = 2) -> np.ndarray:
    """Instance positions registered by their corresponding features.

    A stage-I box is the hull of the features an instance happens to have, so a partial
    instance has a shifted box centre. Each visual word m has a typical offset from the
    instance centre, ``o_m = median_k (p_mk - c_k)``; the registered centre of instance
    k is ``median_m (p_mk - o_m)`` over its words (the box centre with fewer than
    ``min_words`` words, e.g. instances added by stage II).

    Parameters
    ----------
    centres : (N, 2) float
        Box centres, pixels.
    feature_points : (M, N', 2) float or None
        Corresponding features, pixels, NaN where missing (N' <= N).
    min_words : int

    Returns
    -------
    (N, 2) float, pixels
    """
    c, fp = checked_points(centres, feature_points)
    if fp is None or fp.shape[0] == 0:
        return c.copy()
    fp = fp[:, :len(c)]
    fin = np.all(np.isfinite(fp), axis=2)  # (M, N)
    with np.errstate(invalid="ignore"):
        off = np.nanmedian(np.where(fin[..., None], fp - c[None], np.nan), axis=1)  # (M, 2)
    out = c.copy()
    for k in range(len(c)):
        ok = fin[:, k] & np.all(np.isfinite(off), axis=1)
        if ok.sum() >= min_words:
            out[k] = np.median(fp[ok, k] - off[ok], axis=0)
    return out


def duplicate_instances(centres: np.ndarray, sizes: np.ndarray,
                        feature_points: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: instances that duplicate another one (centres closer than half the
    smaller of the two sizes); of each such pair the one with fewer features (then the
    later index) is the duplicate.

    >>> duplicate_instances(np.array([[10, 10], [12, 10], [40, 10]]), np.full(3, 10.0)).tolist()
    [False, True, False]
    """
    c = np.asarray(centres, float).reshape(-1, 2)
    sz = np.asarray(sizes, float).reshape(-1)
    n = len(c)
    nfeat = np.zeros(n)
    if feature_points is not None:
        fp = np.asarray(feature_points, float)
        nf = np.all(np.isfinite(fp), axis=2).sum(axis=0)
        nfeat[:len(nf)] = nf[:n]
    rank = np.lexsort((np.arange(n), -nfeat))  # best first
    dup = np.zeros(n, bool)
    for a_i, a in enumerate(rank):
        if dup[a]:
            continue
        for b in rank[a_i + 1:]:
            if not dup[b] and np.linalg.norm(c[a] - c[b]) < 0.5 * min(sz[a], sz[b]):
                dup[b] = True
    return dup


def pattern_rows(bboxes: np.ndarray, feature_points: np.ndarray | None, params: RowParams
                 ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Instance positions, sizes and rows of one RP.

    Parameters
    ----------
    bboxes : (N, 4) float
        Instance boxes ``[x, y, w, h]``, pixels.
    feature_points : (M, N', 2) float or None
        Corresponding features, pixels, NaN where missing (N' <= N).
    params : RowParams
        ``register_centres``, ``row_tolerance``, ``min_row_instances`` (a ``VPParams``).

    Returns
    -------
    centres : (N, 2) float
        Registered centres (:func:`registered_centres`) when ``params.register_centres``,
        else box centres, pixels.
    sizes : (N,) float
        Smaller box sides, pixels.
    rows : list of int arrays
        :func:`group_rows` on the non-duplicate instances (original indices).
    """
    c, sz = instance_centres_sizes(bboxes)
    keep = np.arange(len(c))
    if params.register_centres and len(c) >= 2:
        c = registered_centres(c, feature_points)
        keep = np.nonzero(~duplicate_instances(c, sz, feature_points))[0]
    if len(keep) < 2:
        return c, sz, []
    rows = group_rows(c[keep], sz[keep], params.row_tolerance, params.min_row_instances)
    return c, sz, [keep[r] for r in rows]
