"""URP-based search for RP matrices Omega (RESCU-I, the improvement over GRASP).

One search starts from an initial URP (a 2 x 2 matrix) and grows it by

* **add column** (a new instance): every feature matched (by descriptor) to an entry of
  row i votes for the frame (centre ``C``, scale ``sigma``) the new instance would have
  if it held that feature as word i; frames with votes from several rows are
  hypotheses. For each hypothesis and row i the entry is, among the features near the
  predicted position whose descriptor matches the row, the one maximising
  ``V(f | Omega) = sum_{j <= q, k != i} u(f_{i,q+1}, f_{i,j}, f_{k,q+1}, f_{k,j})``
  (the paper's V); rows whose mean V is below ``u_min`` stay empty (-1).
* **add row** (a new visual word): each unused feature inside the reference instance
  predicts where its copies lie in the other instances; a copy is the nearest feature
  there with a matching descriptor; the row is kept when its mean affinity with the
  existing rows (V summed over instance pairs) reaches ``u_min``.
* **remove column / row**: entries, rows and columns whose mean affinity falls below
  ``u_min``, or with fewer than two entries, are dropped.

Instances may not overlap: a new column whose feature box overlaps an existing
instance box (IoU > ``max_overlap``) is refused, and a new word may not put a feature
inside another instance's box. This is what keeps an instance on one window of a grid
of identical windows instead of spanning two.

Positions are predicted with a similarity frame per instance (centroid ``c_j`` and
scale ``sigma_j`` = median keypoint size of the column), so instances may differ in
size, as under perspective.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .urp import Gates, objective, urp_affinity


@dataclass
class SearchContext:
    """Everything a search needs, precomputed once per image.

    Attributes
    ----------
    xy : (K, 2) float64, pixels; scale : (K,) float64, pixels; angle : (K,) float64, deg.
    rs : (K, 128) float32
        RootSIFT descriptors (unit L2).
    nbr : (K, k) int64
        Candidate correspondences (descriptor neighbours), -1 padded.
    tree : cKDTree over ``xy``.
    """

    xy: np.ndarray
    scale: np.ndarray
    angle: np.ndarray
    rs: np.ndarray
    nbr: np.ndarray
    tree: cKDTree
    sigma_s: float = 0.2
    sigma_theta: float = 0.2
    orientation_mode: str = "wrapped"
    desc_max_dist: float = 0.5
    pos_tol: float = 0.2
    u_min: float = 0.5
    min_fill: float = 0.5
    max_overlap: float = 0.2
    row_expand: float = 0.25
    max_rows: int = 60
    max_cols: int = 200
    max_iters: int = 30
    col_hypotheses: int = 8
    row_candidates: int = 150
    v_rows: int = 8
    extra: dict = field(default_factory=dict)

    def u(self, f11: np.ndarray, f12: np.ndarray, f21: np.ndarray, f22: np.ndarray,
          gates: Gates) -> np.ndarray:
        return urp_affinity(self.xy, self.scale, self.angle, f11, f12, f21, f22,
                            self.sigma_s, self.sigma_theta, self.orientation_mode, gates)


def column_boxes(xy: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Feature hull ``[x0, y0, x1, y1]`` of every column of ``omega`` (N, 4), pixels."""
    n = omega.shape[1]
    out = np.zeros((n, 4))
    for j in range(n):
        idx = omega[:, j][omega[:, j] >= 0]
        p = xy[idx]
        out[j] = [p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()]
    return out


def _iou_xyxy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a.reshape(-1, 4)
    b = b.reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    area = lambda z: np.maximum(z[:, 2] - z[:, 0], 1.0) * np.maximum(z[:, 3] - z[:, 1], 1.0)  # noqa: E731
    return inter / (area(a)[:, None] + area(b)[None, :] - inter)


def _nanmedian(a: np.ndarray, axis: int) -> np.ndarray:
    """Median ignoring NaN along ``axis`` (NaN where all are NaN); a fast stand-in for
    ``np.nanmedian``, which is slow on the many small arrays of a search."""
    srt = np.sort(a, axis=axis)                          # NaN sort last
    n = np.sum(~np.isnan(a), axis=axis, keepdims=True)
    lo = np.maximum((n - 1) // 2, 0)
    hi = np.maximum(n // 2, 0)
    v = 0.5 * (np.take_along_axis(srt, lo, axis) + np.take_along_axis(srt, hi, axis))
    v = np.where(n > 0, v, np.nan)
    return np.squeeze(v, axis=axis)


def _frames(ctx: SearchContext, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column centroids (N, 2), column scales (N,), row offset templates (M, 2)."""
    pres = omega >= 0
    idx = np.where(pres, omega, 0)
    p = ctx.xy[idx]                                     # (M, N, 2)
    cnt = pres.sum(0)
    c = (p * pres[..., None]).sum(0) / np.maximum(cnt, 1)[:, None]
    s = np.array([np.median(ctx.scale[omega[:, j][pres[:, j]]]) for j in range(omega.shape[1])])
    off = (p - c[None]) / s[None, :, None]
    off = np.where(pres[..., None], off, np.nan)
    with np.errstate(all="ignore"):
        tmpl = _nanmedian(off, axis=1)                # (M, 2)
        # consistent frame centres: a column missing some words would otherwise have
        # its centroid shifted; c_j = median over words of (p_ij - sigma_j * tmpl_i)
        cc = np.where(pres[..., None], p - s[None, :, None] * tmpl[:, None, :], np.nan)
        c2 = _nanmedian(cc, axis=0)
        c = np.where(np.isfinite(c2), c2, c)
        off = np.where(pres[..., None], (p - c[None]) / s[None, :, None], np.nan)
        tmpl = _nanmedian(off, axis=1)
    return c, s, tmpl


def _desc_ok(ctx: SearchContext, cand: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Whether candidate features match reference features (RootSIFT distance).

    cand : (E,) int; ref : (E, R) int with -1 padding. Returns (E,) bool: the distance
    to the closest reference is at most ``desc_max_dist``.
    """
    ok_ref = ref >= 0
    dots = np.einsum("ed,erd->er", ctx.rs[cand], ctx.rs[np.where(ok_ref, ref, 0)])
    d2 = np.where(ok_ref, 2.0 - 2.0 * dots, np.inf).min(axis=1)
    return d2 <= ctx.desc_max_dist ** 2


def add_columns(ctx: SearchContext, omega: np.ndarray, available: np.ndarray,
                gates: Gates) -> np.ndarray:
    """Add new instances (columns) to ``omega`` (M, N); returns the new matrix."""
    m, n = omega.shape
    if n >= ctx.max_cols:
        return omega
    c, s, tmpl = _frames(ctx, omega)
    boxes = column_boxes(ctx.xy, omega)
    size = np.median(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]))
    s_ref = np.median(s)
    used = np.zeros(len(ctx.xy), bool)
    used[omega[omega >= 0]] = True
    # votes: (row i, column j, matched feature h)
    ii, jj = np.nonzero(omega >= 0)
    f = omega[ii, jj]
    h = ctx.nbr[f]                                      # (P, k)
    ii = np.repeat(ii, h.shape[1])
    jj = np.repeat(jj, h.shape[1])
    f = np.repeat(f, h.shape[1])
    h = h.ravel()
    ok = h >= 0
    ok[ok] = available[h[ok]] & ~used[h[ok]]
    ii, jj, f, h = ii[ok], jj[ok], f[ok], h[ok]
    if len(h) == 0:
        return omega
    sig = ctx.scale[h] / ctx.scale[f] * s[jj]           # sigma of the new instance
    # its centre C: h sits in the new instance where f sits in instance j (local frame,
    # so instances that change shape along a row under perspective still agree)
    cen = ctx.xy[h] - (ctx.scale[h] / ctx.scale[f])[:, None] * (ctx.xy[f] - c[jj])
    cell = max(3.0, ctx.pos_tol * size)
    key = np.floor(cen / cell).astype(np.int64)
    # distinct rows voting per cell
    kr = np.unique(np.stack([key[:, 0], key[:, 1], ii], 1), axis=0)
    # a cell's votes: distinct rows voting in it or its 8 neighbours (a cluster of
    # predicted centres may straddle a cell border)
    sh = np.array([[dx, dy, 0] for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
    kr9 = np.unique((kr[None] + sh[:, None]).reshape(-1, 3), axis=0)
    own = np.unique(kr[:, :2], axis=0)
    cells, votes = np.unique(kr9[:, :2], axis=0, return_counts=True)
    has = np.zeros(len(cells), bool)
    pos = np.searchsorted(cells[:, 0] * (1 << 32) + cells[:, 1], own[:, 0] * (1 << 32) + own[:, 1])
    has[pos] = True
    cells, votes = cells[has], votes[has]
    order = np.lexsort((cells[:, 1], cells[:, 0], -votes))
    cells, votes = cells[order], votes[order]
    keep = votes >= 2
    cells = cells[keep][: ctx.col_hypotheses * 3]
    new_cols: list[np.ndarray] = []
    new_boxes: list[np.ndarray] = []
    n_hyp = 0
    for cl in cells:
        if n_hyp >= ctx.col_hypotheses or n + len(new_cols) >= ctx.max_cols:
            break
        sel = np.all(key == cl, axis=1)
        C0 = np.median(cen[sel], axis=0)
        near = np.hypot(*(cen - C0).T) <= cell
        C = np.median(cen[near], axis=0)
        sg = float(np.median(sig[near]))
        if np.any((C[0] >= boxes[:, 0]) & (C[0] <= boxes[:, 2]) & (C[1] >= boxes[:, 1])
                  & (C[1] <= boxes[:, 3])):
            continue
        if new_boxes and np.any([(C[0] >= b[0]) & (C[0] <= b[2]) & (C[1] >= b[1]) & (C[1] <= b[3])
                                 for b in new_boxes]):
            continue
        n_hyp += 1
        # template: the nearest existing instance, where it has the word (local frame)
        jn = int(np.argmin(np.hypot(*(c - C).T)))
        loc = (ctx.xy[np.where(omega[:, jn] >= 0, omega[:, jn], 0)] - c[jn]) / s[jn]
        tm = np.where((omega[:, jn] >= 0)[:, None], loc, tmpl)
        col = _build_column(ctx, omega, C, sg, tm, size * sg / s_ref, available, used, gates)
        if col is None:
            continue
        pb = ctx.xy[col[col >= 0]]
        box = np.array([pb[:, 0].min(), pb[:, 1].min(), pb[:, 0].max(), pb[:, 1].max()])
        allb = np.vstack([boxes] + ([np.array(new_boxes)] if new_boxes else []))
        if _iou_xyxy(box, allb).max() > ctx.max_overlap:
            continue
        new_cols.append(col)
        new_boxes.append(box)
        used[col[col >= 0]] = True
    if not new_cols:
        return omega
    return np.hstack([omega, np.stack(new_cols, 1)])


def _build_column(ctx: SearchContext, omega: np.ndarray, C: np.ndarray, sg: float,
                  tmpl: np.ndarray, size: float, available: np.ndarray, used: np.ndarray,
                  gates: Gates) -> np.ndarray | None:
    m, n = omega.shape
    rows = np.nonzero(np.all(np.isfinite(tmpl), axis=1))[0]
    pred = C[None] + sg * tmpl[rows]
    rad = ctx.pos_tol * size + 2.0
    dd, qq = ctx.tree.query(pred, k=4, distance_upper_bound=rad)
    rr = np.repeat(rows, 4)
    qq = qq.ravel()
    dd = dd.ravel()
    ok = np.isfinite(dd)
    rr, qq, dd = rr[ok], qq[ok], dd[ok]
    ok = available[qq] & ~used[qq]
    rr, qq, dd = rr[ok], qq[ok], dd[ok]
    if len(qq) == 0:
        return None
    ok = _desc_ok(ctx, qq, omega[rr])
    rr, qq, dd = rr[ok], qq[ok], dd[ok]
    if len(np.unique(rr)) < 2:
        return None
    # provisional column: nearest candidate per row
    o = np.lexsort((qq, dd, rr))
    rr, qq, dd = rr[o], qq[o], dd[o]
    first = np.r_[True, rr[1:] != rr[:-1]]
    col = np.full(m, -1, np.int64)
    col[rr[first]] = qq[first]
    # V(f | Omega) of every candidate against the provisional other rows
    ks = np.nonzero(col >= 0)[0]
    f11 = qq[:, None, None]                       # (E, 1, 1) word i, new instance
    f12 = omega[rr][:, None, :]                   # (E, 1, N) word i, instance j
    f21 = col[ks][None, :, None]                  # (1, R, 1) word k, new instance
    f22 = omega[ks][None, :, :]                   # (1, R, N) word k, instance j
    u = ctx.u(f11, f12, f21, f22, gates)
    u = np.where(rr[:, None, None] == ks[None, :, None], 0.0, u)
    V = u.sum(axis=(1, 2))                        # V(f | Omega)
    cnt = ((f12 >= 0) & (f22 >= 0) & (rr[:, None, None] != ks[None, :, None])).sum(axis=(1, 2))
    meanV = V / np.maximum(cnt, 1)
    o = np.lexsort((qq, -V, rr))
    rr, qq, meanV = rr[o], qq[o], meanV[o]
    first = np.r_[True, rr[1:] != rr[:-1]]
    col = np.full(m, -1, np.int64)
    good = first & (meanV >= ctx.u_min)
    col[rr[good]] = qq[good]
    vals, cts = np.unique(col[col >= 0], return_counts=True)
    for v in vals[cts > 1]:                       # one feature, one word
        dup = np.nonzero(col == v)[0]
        col[dup[1:]] = -1
    if (col >= 0).sum() < max(2, int(np.ceil(0.5 * ctx.min_fill * m))):
        return None
    return col


def add_rows(ctx: SearchContext, omega: np.ndarray, available: np.ndarray,
             gates: Gates) -> np.ndarray:
    """Add new visual words (rows) to ``omega`` (M, N); returns the new matrix."""
    m, n = omega.shape
    if m >= ctx.max_rows:
        return omega
    c, s, _ = _frames(ctx, omega)
    boxes = column_boxes(ctx.xy, omega)
    fill = (omega >= 0).sum(0)
    jr = int(np.argmax(fill))
    b = boxes[jr]
    bw, bh = b[2] - b[0], b[3] - b[1]
    # candidate region: the reference box grown by row_expand of its size, or up to half
    # the spacing to the nearest other instance (an instance is at most one period wide),
    # never beyond P_d / 2 from the centroid
    dc = np.hypot(*(c - c[jr]).T)
    dc[jr] = np.inf
    half = 0.5 * float(dc.min()) if n > 1 else 0.0
    # the period seen by the reference features: distance to their nearest copy
    fr = omega[:, jr][omega[:, jr] >= 0]
    nb = ctx.nbr[fr]
    dn = np.where(nb >= 0, np.hypot(ctx.xy[np.where(nb >= 0, nb, 0), 0] - ctx.xy[fr, None, 0],
                                    ctx.xy[np.where(nb >= 0, nb, 0), 1] - ctx.xy[fr, None, 1]),
                  np.inf).min(1)
    dn = dn[np.isfinite(dn)]
    if len(dn):
        half = min(half, 0.5 * float(np.median(dn)))
    lim = gates.max_dist / 2.0
    if half > 0:
        # an instance is at most one period wide: never grow beyond half the spacing
        rx = min(lim, max(bw / 2.0, half))
        ry = min(lim, max(bh / 2.0, half))
    else:
        rx = min(lim, bw / 2.0 + ctx.row_expand * max(bw, bh))
        ry = min(lim, bh / 2.0 + ctx.row_expand * max(bw, bh))
    cx, cy = (b[0] + b[2]) / 2.0, (b[1] + b[3]) / 2.0
    x0, x1 = cx - rx, cx + rx
    y0, y1 = cy - ry, cy + ry
    used = np.zeros(len(ctx.xy), bool)
    used[omega[omega >= 0]] = True
    cand = np.nonzero(available & ~used & (ctx.xy[:, 0] >= x0) & (ctx.xy[:, 0] <= x1)
                      & (ctx.xy[:, 1] >= y0) & (ctx.xy[:, 1] <= y1))[0]
    if len(cand) == 0:
        return omega
    # not inside another instance
    others = np.delete(boxes, jr, axis=0)
    if len(others):
        inside = ((ctx.xy[cand, None, 0] >= others[None, :, 0]) & (ctx.xy[cand, None, 0] <= others[None, :, 2])
                  & (ctx.xy[cand, None, 1] >= others[None, :, 1]) & (ctx.xy[cand, None, 1] <= others[None, :, 3]))
        cand = cand[~inside.any(1)]
    cand = cand[: ctx.row_candidates]  # features are sorted by response
    e = len(cand)
    if e == 0:
        return omega
    size = np.median(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]))
    ratio = s / s[jr]                                   # (N,)
    pred = c[None] + ratio[None, :, None] * (ctx.xy[cand][:, None, :] - c[jr][None, None])  # (E, N, 2)
    rad = ctx.pos_tol * size * ratio + 2.0              # (N,)
    dd, qq = ctx.tree.query(pred.reshape(-1, 2), k=4, distance_upper_bound=float(rad.max()))
    dd = dd.reshape(e, n, 4)
    qq = qq.reshape(e, n, 4)
    ok = dd <= rad[None, :, None]
    qs = np.where(ok, qq, 0)
    ok &= available[qs] & ~used[qs]
    dots = np.einsum("ed,enkd->enk", ctx.rs[cand], ctx.rs[qs])
    ok &= (2.0 - 2.0 * dots) <= ctx.desc_max_dist ** 2
    ok &= qs != cand[:, None, None]
    dd = np.where(ok, dd, np.inf)
    best = np.argmin(dd, axis=2)
    row = np.take_along_axis(qs, best[..., None], 2)[..., 0]
    row = np.where(np.isfinite(np.take_along_axis(dd, best[..., None], 2)[..., 0]), row, -1)
    row[:, jr] = cand                                   # (E, N)
    need = max(2, int(np.ceil(ctx.min_fill * n)))
    keep = (row >= 0).sum(1) >= need
    row, cand = row[keep], cand[keep]
    if len(row) == 0:
        return omega
    # mean affinity of the new row with (a subset of) the existing rows over column pairs
    ks = np.argsort(-(omega >= 0).sum(1), kind="stable")[: ctx.v_rows]
    j1, j2 = np.triu_indices(n, 1)
    f11 = row[:, None, j1]
    f12 = row[:, None, j2]
    f21 = omega[ks][None][:, :, j1]
    f22 = omega[ks][None][:, :, j2]
    u = ctx.u(f11, f12, f21, f22, gates)
    cnt = ((f11 >= 0) & (f12 >= 0) & (f21 >= 0) & (f22 >= 0)).sum(axis=(1, 2))
    meanV = u.sum(axis=(1, 2)) / np.maximum(cnt, 1)
    order = np.argsort(-meanV, kind="stable")
    taken = used.copy()
    add = []
    for r in order:
        if meanV[r] < ctx.u_min or m + len(add) >= ctx.max_rows:
            break
        rw = row[r].copy()
        clash = (rw >= 0) & taken[np.where(rw >= 0, rw, 0)]
        if clash[jr]:
            continue
        rw[clash] = -1
        if (rw >= 0).sum() < need:
            continue
        taken[rw[rw >= 0]] = True
        add.append(rw)
    if not add:
        return omega
    return np.vstack([omega, np.stack(add)])


def prune(ctx: SearchContext, omega: np.ndarray, gates: Gates) -> np.ndarray:
    """Remove entries, rows and columns whose mean URP affinity is below ``u_min / 2``.

    An entry's mean affinity is taken over its URPs with the ``v_rows`` best-filled rows
    and all other columns (bounded cost); rows and columns left with fewer than two
    entries are removed.
    """
    for _ in range(3):
        m, n = omega.shape
        if m < 2 or n < 2:
            return omega
        ks = np.argsort(-(omega >= 0).sum(1), kind="stable")[: max(ctx.v_rows, 2)]
        a = omega[:, None, :, None]       # f11 (m1, n1)
        b = omega[:, None, None, :]       # f12 (m1, n2)
        c_ = omega[ks][None, :, :, None]  # f21 (m2, n1)
        d = omega[ks][None, :, None, :]   # f22 (m2, n2)
        u = ctx.u(a, b, c_, d, gates)     # (M, R, N, N)
        pres = omega >= 0
        pk = pres[ks]
        valid = (pres[:, None, :, None] & pres[:, None, None, :] & pk[None, :, :, None]
                 & pk[None, :, None, :])
        valid &= (np.arange(m)[:, None] != ks[None, :])[:, :, None, None]
        valid &= ~np.eye(n, dtype=bool)[None, None]
        e_sum = (u * valid).sum(axis=(1, 3))          # per entry (m1, n1)
        e_cnt = valid.sum(axis=(1, 3))
        e_mean = np.where(e_cnt > 0, e_sum / np.maximum(e_cnt, 1), 0.0)
        new = np.where(pres & (e_mean >= ctx.u_min * 0.5), omega, -1)
        new = new[(new >= 0).sum(1) >= 2]
        if new.shape[0] < 2:
            return new
        new = new[:, (new >= 0).sum(0) >= 2]
        if new.shape == omega.shape and np.array_equal(new, omega):
            return omega
        omega = new
    return omega


def search(ctx: SearchContext, seed: np.ndarray, available: np.ndarray,
           gates: Gates) -> np.ndarray:
    """Grow an RP matrix from an initial URP.

    Parameters
    ----------
    seed : (4,) int
        ``(f11, f12, f21, f22)``: word 1 in instances 1, 2; word 2 in instances 1, 2.
    available : (K,) bool
        Features that may be used (not taken by an accepted RP).
    gates : Gates

    Returns
    -------
    (M, N) int64
        Feature indices, -1 where a word is missing in an instance.
    """
    omega = np.array([[seed[0], seed[1]], [seed[2], seed[3]]], np.int64)
    for _ in range(ctx.max_iters):
        shape0 = omega.shape
        omega = add_columns(ctx, omega, available, gates)
        omega = add_rows(ctx, omega, available, gates)
        omega = prune(ctx, omega, gates)
        if omega.shape[0] < 2 or omega.shape[1] < 2:
            return omega
        if omega.shape == shape0:
            break
    omega = add_rows(ctx, omega, available, gates)
    return prune(ctx, omega, gates)


def matrix_objective(ctx: SearchContext, omega: np.ndarray, gates: Gates) -> float:
    """U(Omega) with the context's sigma and orientation mode."""
    return objective(ctx.xy, ctx.scale, ctx.angle, omega, ctx.sigma_s, ctx.sigma_theta,
                     ctx.orientation_mode, gates)
