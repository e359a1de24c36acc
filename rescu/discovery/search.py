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

Cost: the hypotheses of one add-column step are built in one vectorised batch
(:func:`_build_columns`, rebuilt after each accepted column so the result equals the
sequential one), a prune reuses its first pass's affinities, and a round that changes
nothing ends the search without repeating its add-row step.

Positions are predicted with a similarity frame per instance (centroid ``c_j`` and
scale ``sigma_j`` = median keypoint size of the column), so instances may differ in
size, as under perspective.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..boxes import iou_matrix_xyxy
from ..params import config_section
from .urp import AffinityParams, AffinityParts, Gates, objective_omega, pairs, urp_affinity


@dataclass(frozen=True)
@config_section("stage1")
class SearchParams:
    """The tunables of one search (config section ``stage1``; defaults from there).
    :class:`rescu.discovery.stage1.Stage1Params` derives from this class.

    Attributes
    ----------
    pos_tol : float
        Position tolerance of a predicted copy, fraction of the instance size.
    u_min : float
        Least mean affinity of a new row / column (and twice the least of an entry).
    min_fill : float
        A new row needs entries in this fraction of the instances (a new column in half
        this fraction of the words).
    max_overlap : float
        Max IoU between feature boxes of two instances.
    row_expand : float
        New words are searched within the reference instance box grown by this
        fraction of its size.
    max_rows, max_cols, max_iters : int
        Size and iteration limits of one search.
    """

    pos_tol: float
    u_min: float
    min_fill: float
    max_overlap: float
    row_expand: float
    max_rows: int
    max_cols: int
    max_iters: int


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
    affinity : AffinityParams
    desc_max_dist : float
        Largest RootSIFT distance of a match (stage I's ``match_max_dist``).
    search : SearchParams
        The search's tunables (the caller,
        :func:`rescu.discovery.stage1.search_context`, passes its Stage1Params).
    col_hypotheses, row_candidates, v_rows : int
        Internal limits of one search step.
    """

    xy: np.ndarray
    scale: np.ndarray
    angle: np.ndarray
    rs: np.ndarray
    nbr: np.ndarray
    tree: cKDTree
    affinity: AffinityParams
    desc_max_dist: float
    search: SearchParams
    col_hypotheses: int = 8
    row_candidates: int = 150
    v_rows: int = 8
    extra: dict = field(default_factory=dict)

    def u(self, f11: np.ndarray, f12: np.ndarray, f21: np.ndarray, f22: np.ndarray,
          gates: Gates) -> np.ndarray:
        return urp_affinity(self.xy, self.scale, self.angle, f11, f12, f21, f22,
                            self.affinity, gates)

    def parts(self, f11: np.ndarray, f12: np.ndarray, f21: np.ndarray,
              f22: np.ndarray) -> AffinityParts:
        """Ungated affinities with their gate quantities (gate them with ``.gated``)."""
        return urp_affinity(self.xy, self.scale, self.angle, f11, f12, f21, f22,
                            self.affinity, return_parts=True)


def column_boxes(xy: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Feature hull ``[x0, y0, x1, y1]`` of every column of ``omega`` (N, 4), pixels.

    Every column must hold at least one feature (vectorised over the columns)."""
    pres = omega >= 0
    p = xy[np.where(pres, omega, 0)]                    # (M, N, 2)
    lo = np.where(pres[..., None], p, np.inf).min(axis=0)
    hi = np.where(pres[..., None], p, -np.inf).max(axis=0)
    if not np.all(np.isfinite(lo)):
        raise ValueError("column_boxes: every column of omega needs a feature")
    return np.concatenate([lo, hi], axis=1).astype(np.float64)


def _median(a: np.ndarray) -> np.ndarray:
    """Median along axis 0 (same values as ``np.median(a, axis=0)`` for NaN-free input,
    without its per-call overhead on the many tiny arrays of a search)."""
    srt = np.sort(a, axis=0)
    k = srt.shape[0]
    if k % 2:
        return srt[k // 2]
    return (srt[k // 2 - 1] + srt[k // 2]) / 2.0


def _nanmedian(a: np.ndarray, axis: int) -> np.ndarray:
    """Median ignoring NaN along ``axis`` (NaN where all are NaN); a fast stand-in for
    ``np.nanmedian``, which is slow on the many small arrays of a search."""
    b = np.moveaxis(a, axis, -1)
    k = b.shape[-1]
    nan = np.isnan(b)
    if k and not nan.any():                              # complete: a plain median
        srt = np.sort(b, axis=-1)
        if k % 2:
            return srt[..., k // 2]
        return 0.5 * (srt[..., k // 2 - 1] + srt[..., k // 2])
    n = k - nan.sum(axis=-1)
    if k == 0:
        return np.full(n.shape, np.nan)
    srt = np.sort(b, axis=-1).reshape(-1, k)             # NaN sort last
    lo = np.maximum((n - 1) // 2, 0).ravel()
    hi = np.maximum(n // 2, 0).ravel()
    r = np.arange(len(srt))
    v = (0.5 * (srt[r, lo] + srt[r, hi])).reshape(n.shape)
    return np.where(n > 0, v, np.nan)


def _unique(a: np.ndarray, return_counts: bool = False):
    """Sorted unique values of a 1-D int array (``np.unique`` without its overhead)."""
    a = np.sort(a)
    first = np.empty(len(a), bool)
    first[:1] = True
    first[1:] = a[1:] != a[:-1]
    if not return_counts:
        return a[first]
    start = np.nonzero(first)[0]
    return a[start], np.diff(np.r_[start, len(a)])


def _frames(ctx: SearchContext, omega: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Column centroids (N, 2), column scales (N,), row offset templates (M, 2) and
    column boxes (N, 4) (:func:`column_boxes`) of ``omega`` (M, N), pixels."""
    cached = ctx.extra.get("_frames")
    if cached is not None and cached[0].shape == omega.shape and np.array_equal(cached[0], omega):
        return cached[1]                                # add_rows right after add_columns
    pres = omega >= 0
    idx = np.where(pres, omega, 0)
    p = ctx.xy[idx]                                     # (M, N, 2)
    cnt = pres.sum(0)
    c = (p * pres[..., None]).sum(0) / np.maximum(cnt, 1)[:, None]
    with np.errstate(all="ignore"):
        s = _nanmedian(np.where(pres, ctx.scale[idx], np.nan), axis=0)  # sigma_j
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
    boxes = column_boxes(ctx.xy, omega)
    ctx.extra["_frames"] = (omega.copy(), (c, s, tmpl, boxes))
    return c, s, tmpl, boxes


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
    """Add new instances (columns) to ``omega`` (M, N) int64, up to ``max_cols`` columns.

    Returns the (M, N') matrix with the new columns appended, or ``omega`` itself (the
    same object) when none is added: :func:`search` tells an idle round by identity.
    """
    m, n = omega.shape
    if n >= ctx.search.max_cols:
        return omega
    c, s, tmpl, boxes = _frames(ctx, omega)
    size = _median(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]))
    s_ref = _median(s)
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
    cell = max(3.0, ctx.search.pos_tol * size)
    key = np.floor(cen / cell).astype(np.int64)
    # cells as 1-D codes in (kx, ky) lexicographic order, with a margin of one cell
    kx = key[:, 0] - (key[:, 0].min() - 1)
    ky = key[:, 1] - (key[:, 1].min() - 1)
    hgt = int(ky.max()) + 2
    code = kx * hgt + ky                                # cell code of every vote
    # distinct rows voting per cell
    kr = _unique(code * m + ii)
    # a cell's votes: distinct rows voting in it or its 8 neighbours (a cluster of
    # predicted centres may straddle a cell border)
    sh = np.array([(dx * hgt + dy) * m for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
    kr9 = _unique((kr[None] + sh[:, None]).ravel())
    own = _unique(kr // m)
    cells, votes = _unique(kr9 // m, return_counts=True)
    has = np.zeros(len(cells), bool)
    has[np.searchsorted(cells, own)] = True
    cells, votes = cells[has], votes[has]
    order = np.lexsort((cells, -votes))
    cells, votes = cells[order], votes[order]
    keep = votes >= 2
    cells = cells[keep][: ctx.col_hypotheses * 3]
    new_cols: list[np.ndarray] = []
    new_boxes: list[np.ndarray] = []
    n_hyp = 0
    frame_of: dict[int, tuple[np.ndarray, float]] = {}

    def frame(ci: int) -> tuple[np.ndarray, float]:
        # centre C and scale sigma of the instance a cell hypothesises (no state)
        if ci not in frame_of:
            C0 = _median(cen[code == cells[ci]])
            near = np.hypot(cen[:, 0] - C0[0], cen[:, 1] - C0[1]) <= cell
            frame_of[ci] = (_median(cen[near]), float(_median(sig[near])))
        return frame_of[ci]

    # The hypotheses are tried in order, and an accepted column changes the state
    # (used features, new boxes) the later ones see. They are built in batches
    # (_build_columns, one vectorised pass): a batch holds the next hypotheses as if
    # none of them is accepted; after the first accepted one the rest of the batch is
    # discarded and rebuilt from the new state, so the result equals the sequential one.
    ptr = 0
    while ptr < len(cells):
        pending = []
        n_h = n_hyp
        for ci in range(ptr, len(cells)):
            if n_h >= ctx.col_hypotheses or n + len(new_cols) >= ctx.search.max_cols:
                break
            C, sg = frame(ci)
            if np.any((C[0] >= boxes[:, 0]) & (C[0] <= boxes[:, 2]) & (C[1] >= boxes[:, 1])
                      & (C[1] <= boxes[:, 3])):
                continue
            if new_boxes and np.any([(C[0] >= b[0]) & (C[0] <= b[2]) & (C[1] >= b[1])
                                     & (C[1] <= b[3]) for b in new_boxes]):
                continue
            n_h += 1
            # template: the nearest existing instance, where it has the word (local frame)
            jn = int(np.argmin(np.hypot(c[:, 0] - C[0], c[:, 1] - C[1])))
            loc = (ctx.xy[np.where(omega[:, jn] >= 0, omega[:, jn], 0)] - c[jn]) / s[jn]
            tm = np.where((omega[:, jn] >= 0)[:, None], loc, tmpl)
            pending.append((ci, C, sg, tm, size * sg / s_ref))
        if not pending:
            break
        cols = _build_columns(ctx, omega, np.array([h[1] for h in pending]),
                              np.array([h[2] for h in pending]),
                              np.stack([h[3] for h in pending]),
                              np.array([h[4] for h in pending]), available, used, gates)
        accepted = False
        for (ci, *_), col in zip(pending, cols):
            n_hyp += 1
            ptr = ci + 1
            if col is None:
                continue
            pb = ctx.xy[col[col >= 0]]
            box = np.array([pb[:, 0].min(), pb[:, 1].min(), pb[:, 0].max(), pb[:, 1].max()])
            allb = np.vstack([boxes] + ([np.array(new_boxes)] if new_boxes else []))
            if iou_matrix_xyxy(box, allb).max() > ctx.search.max_overlap:
                continue
            new_cols.append(col)
            new_boxes.append(box)
            used[col[col >= 0]] = True
            accepted = True
            break
        if not accepted:
            break
    if not new_cols:
        return omega
    return np.hstack([omega, np.stack(new_cols, 1)])


def _build_columns(ctx: SearchContext, omega: np.ndarray, C: np.ndarray, sg: np.ndarray,
                   tmpl: np.ndarray, size: np.ndarray, available: np.ndarray,
                   used: np.ndarray, gates: Gates) -> list[np.ndarray | None]:
    """:func:`_build_column` for H hypotheses at once (independent of each other).

    C : (H, 2) float, pixels; sg : (H,) float; tmpl : (H, M, 2) float; size : (H,)
    float, pixels. Returns H columns ((M,) int64, -1 for missing) or None.
    """
    m, n = omega.shape
    nh = len(C)
    fin = np.all(np.isfinite(tmpl), axis=2)            # (H, M)
    hh, rows = np.nonzero(fin)
    pred = C[hh] + sg[hh, None] * tmpl[hh, rows]
    rad = ctx.search.pos_tol * size + 2.0                      # (H,)
    out: list[np.ndarray | None] = [None] * nh
    if len(hh) == 0:
        return out
    dd, qq = ctx.tree.query(pred, k=4, distance_upper_bound=float(rad.max()))
    hh = np.repeat(hh, 4)
    rr = np.repeat(rows, 4)
    qq = qq.ravel()
    dd = dd.ravel()
    ok = dd < rad[hh]                                   # as a query bounded by rad
    hh, rr, qq, dd = hh[ok], rr[ok], qq[ok], dd[ok]
    ok = available[qq] & ~used[qq]
    hh, rr, qq, dd = hh[ok], rr[ok], qq[ok], dd[ok]
    if len(qq) == 0:
        return out
    ok = _desc_ok(ctx, qq, omega[rr])
    hh, rr, qq, dd = hh[ok], rr[ok], qq[ok], dd[ok]
    # a hypothesis needs candidates for two words
    hr = _unique(hh * m + rr)
    nrows = np.bincount(hr // m, minlength=nh)
    ok = nrows[hh] >= 2
    hh, rr, qq, dd = hh[ok], rr[ok], qq[ok], dd[ok]
    if len(qq) == 0:
        return out
    # provisional columns: nearest candidate per (hypothesis, row)
    o = np.lexsort((qq, dd, rr, hh))
    hh, rr, qq, dd = hh[o], rr[o], qq[o], dd[o]
    first = np.r_[True, (rr[1:] != rr[:-1]) | (hh[1:] != hh[:-1])]
    prov = np.full((nh, m), -1, np.int64)
    prov[hh[first], rr[first]] = qq[first]
    # V(f | Omega) of every candidate against the provisional other rows of its column
    ks = np.arange(m)
    f11 = qq[:, None, None]                       # (E, 1, 1) word i, new instance
    f12 = omega[rr][:, None, :]                   # (E, 1, N) word i, instance j
    f21 = prov[hh][:, :, None]                    # (E, M, 1) word k, new instance
    f22 = omega[None, :, :]                       # (1, M, N) word k, instance j
    other = rr[:, None, None] != ks[None, :, None]
    u = np.where(other, ctx.u(f11, f12, f21, f22, gates), 0.0)
    V = u.sum(axis=(1, 2))                        # V(f | Omega)
    cnt = ((f12 >= 0) & (f22 >= 0) & (f21 >= 0) & other).sum(axis=(1, 2))
    meanV = V / np.maximum(cnt, 1)
    o = np.lexsort((qq, -V, rr, hh))
    hh, rr, qq, meanV = hh[o], rr[o], qq[o], meanV[o]
    first = np.r_[True, (rr[1:] != rr[:-1]) | (hh[1:] != hh[:-1])]
    good = first & (meanV >= ctx.search.u_min)
    cols = np.full((nh, m), -1, np.int64)
    cols[hh[good], rr[good]] = qq[good]
    # one feature, one word: a feature chosen for several words keeps the first
    ch, cr = np.nonzero(cols >= 0)
    cv = cols[ch, cr]
    o = np.lexsort((cr, cv, ch))
    ch, cr, cv = ch[o], cr[o], cv[o]
    dup = np.zeros(len(cv), bool)
    dup[1:] = (cv[1:] == cv[:-1]) & (ch[1:] == ch[:-1])
    cols[ch[dup], cr[dup]] = -1
    need = max(2, int(np.ceil(0.5 * ctx.search.min_fill * m)))
    for h in np.nonzero((cols >= 0).sum(1) >= need)[0]:
        out[h] = cols[h]
    return out


def _build_column(ctx: SearchContext, omega: np.ndarray, C: np.ndarray, sg: float,
                  tmpl: np.ndarray, size: float, available: np.ndarray, used: np.ndarray,
                  gates: Gates) -> np.ndarray | None:
    """The new column (M,) int64 of the instance with centre ``C`` (2,), scale ``sg`` and
    word template ``tmpl`` (M, 2), or None: per word the nearest matching feature near
    the predicted position, then per word the candidate maximising V(f | Omega)."""
    return _build_columns(ctx, omega, np.asarray(C, np.float64)[None], np.array([sg], float),
                          np.asarray(tmpl, np.float64)[None], np.array([size], float),
                          available, used, gates)[0]


def add_rows(ctx: SearchContext, omega: np.ndarray, available: np.ndarray,
             gates: Gates) -> np.ndarray:
    """Add new visual words (rows) to ``omega`` (M, N) int64, up to ``max_rows`` rows.

    Returns the (M', N) matrix with the new rows appended, or ``omega`` itself (the same
    object) when none is added (see :func:`add_columns`).
    """
    m, n = omega.shape
    if m >= ctx.search.max_rows:
        return omega
    c, s, _, boxes = _frames(ctx, omega)
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
        half = min(half, 0.5 * float(_median(dn)))
    lim = gates.max_dist / 2.0
    if half > 0:
        # an instance is at most one period wide: never grow beyond half the spacing
        rx = min(lim, max(bw / 2.0, half))
        ry = min(lim, max(bh / 2.0, half))
    else:
        rx = min(lim, bw / 2.0 + ctx.search.row_expand * max(bw, bh))
        ry = min(lim, bh / 2.0 + ctx.search.row_expand * max(bw, bh))
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
    size = _median(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]))
    ratio = s / s[jr]                                   # (N,)
    pred = c[None] + ratio[None, :, None] * (ctx.xy[cand][:, None, :] - c[jr][None, None])  # (E, N, 2)
    rad = ctx.search.pos_tol * size * ratio + 2.0              # (N,)
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
    need = max(2, int(np.ceil(ctx.search.min_fill * n)))
    keep = (row >= 0).sum(1) >= need
    row, cand = row[keep], cand[keep]
    if len(row) == 0:
        return omega
    # mean affinity of the new row with (a subset of) the existing rows over column pairs
    ks = np.argsort(-(omega >= 0).sum(1), kind="stable")[: ctx.v_rows]
    j1, j2 = pairs(n)
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
        if meanV[r] < ctx.search.u_min or m + len(add) >= ctx.search.max_rows:
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


def prune(ctx: SearchContext, omega: np.ndarray, gates: Gates,
          first_parts: dict | None = None) -> np.ndarray:
    """Remove entries, rows and columns whose mean URP affinity is below ``u_min / 2``.

    An entry's mean affinity is taken over its URPs with the ``v_rows`` best-filled rows
    and all other columns (bounded cost); rows and columns left with fewer than two
    entries are removed.

    The affinities of the first pass are reused by the later passes (pruning only
    removes entries, rows and columns, so a remaining URP keeps its u); they are
    recomputed only when the best-filled rows change to rows not computed before.
    ``first_parts`` (a dict, filled on first use) shares the ungated first pass among
    calls that prune the same ``omega`` under different gates (the adaptive grid).
    """
    rid = np.arange(omega.shape[0])       # rows / columns of the input matrix
    cid = np.arange(omega.shape[1])
    u0: np.ndarray | None = None
    ks0 = np.zeros(0, np.int64)
    for _ in range(3):
        m, n = omega.shape
        if m < 2 or n < 2:
            return omega
        ks = np.argsort(-(omega >= 0).sum(1), kind="stable")[: max(ctx.v_rows, 2)]
        pos = np.searchsorted(ks0, rid[ks]) if len(ks0) else None
        if u0 is not None and np.all(pos < len(ks0)) and np.array_equal(ks0[pos], rid[ks]):
            u = u0[np.ix_(rid, pos, cid, cid)]
        else:
            a = omega[:, None, :, None]       # f11 (m1, n1)
            b = omega[:, None, None, :]       # f12 (m1, n2)
            c_ = omega[ks][None, :, :, None]  # f21 (m2, n1)
            d = omega[ks][None, :, None, :]   # f22 (m2, n2)
            if u0 is None and first_parts is not None:
                if "parts" not in first_parts:
                    first_parts["parts"] = ctx.parts(a, b, c_, d)
                u = first_parts["parts"].gated(gates)
            else:
                u = ctx.u(a, b, c_, d, gates)     # (M, R, N, N)
            if u0 is None:                    # cache, second axis sorted by row id
                o = np.argsort(ks)
                u0, ks0 = u[:, o], ks[o]
        pres = omega >= 0
        pk = pres[ks]
        valid = (pres[:, None, :, None] & pres[:, None, None, :] & pk[None, :, :, None]
                 & pk[None, :, None, :])
        valid &= (np.arange(m)[:, None] != ks[None, :])[:, :, None, None]
        valid &= ~np.eye(n, dtype=bool)[None, None]
        e_sum = (u * valid).sum(axis=(1, 3))          # per entry (m1, n1)
        e_cnt = valid.sum(axis=(1, 3))
        e_mean = np.where(e_cnt > 0, e_sum / np.maximum(e_cnt, 1), 0.0)
        new = np.where(pres & (e_mean >= ctx.search.u_min * 0.5), omega, -1)
        keep_r = (new >= 0).sum(1) >= 2
        new = new[keep_r]
        if new.shape[0] < 2:
            return new
        keep_c = (new >= 0).sum(0) >= 2
        new = new[:, keep_c]
        if new.shape == omega.shape and np.array_equal(new, omega):
            return omega
        omega = new
        rid, cid = rid[keep_r], cid[keep_c]
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
    idle = False
    for _ in range(ctx.search.max_iters):
        shape0 = omega.shape
        om0 = omega
        om1 = add_columns(ctx, om0, available, gates)
        om2 = add_rows(ctx, om1, available, gates)
        omega = prune(ctx, om2, gates)
        if omega.shape[0] < 2 or omega.shape[1] < 2:
            return omega
        if omega.shape == shape0:
            # nothing was added or removed in this round: the final add-row / prune
            # below would repeat this round's add_rows on the same matrix (a no-op)
            idle = om1 is om0 and om2 is om1 and omega is om2
            break
    if idle:
        return omega
    omega = add_rows(ctx, omega, available, gates)
    return prune(ctx, omega, gates)


def objective_parts(ctx: SearchContext, omega: np.ndarray) -> AffinityParts:
    """The URPs of U(Omega) (all word pairs m1 < m2 times instance pairs n1 < n2),
    ungated, for :func:`matrix_objective` under several gates. omega: (M, N), M, N >= 2."""
    i1, i2 = pairs(omega.shape[0])
    j1, j2 = pairs(omega.shape[1])
    return ctx.parts(omega[i1][:, j1], omega[i1][:, j2], omega[i2][:, j1], omega[i2][:, j2])


def matrix_objective(ctx: SearchContext, omega: np.ndarray, gates: Gates,
                     parts: AffinityParts | None = None) -> float:
    """U(Omega) = 1/(M N) sum of u over its URPs, with the context's sigma and
    orientation mode (as :func:`rescu.discovery.urp.objective`); ``parts`` from
    :func:`objective_parts` of the same omega saves recomputing the affinities."""
    omega = objective_omega(omega, "matrix_objective")
    if omega is None:
        return 0.0
    if parts is None:
        parts = objective_parts(ctx, omega)
    m, n = omega.shape
    return float(parts.gated(gates).sum() / (m * n))
