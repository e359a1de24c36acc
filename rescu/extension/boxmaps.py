"""Box statistics on a frozen CNN's feature map: summed-area tables, the mean feature and
the centre-surround contrast of pixel boxes, how much a set of boxes stands out, and whether
neighbouring boxes are separate things (:func:`separation`), and the local maxima of a map
(:func:`maximum_filter`)
(shared by the dense source, :mod:`rescu.extension.dense`, and the whole-object
selection and confidence, :mod:`rescu.extension.objects`).

Maps are ``(C, h, w)`` float32 arrays whose cells are ``cell_px`` pixels of the map's input
(8 for the dense source's hypercolumn); boxes are ``[x, y, w, h]`` in those pixels.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

__all__ = ["integral_map", "box_contrast", "box_cells", "box_features", "group_prototype",
           "prototype_of", "map_score", "maximum_filter", "unit_mean", "centre_part",
           "OBJECT_PROBE", "separation", "second_boxes", "read_only", "remembered"]


def integral_map(f: np.ndarray) -> np.ndarray:
    """Summed-area table of ``f`` (C, h, w) -> (C, h + 1, w + 1) float64 (for
    :func:`box_contrast`).

    For a read-only ``f`` (the dense source's maps) the table is made once and kept
    while ``f`` lives (:func:`remembered`): the grouping, the completion, the confidence
    and the scoring of stage I's RPs all read the same map's table. It is then read-only
    too."""
    def table() -> np.ndarray:
        c, h, w = f.shape
        ii = np.zeros((c, h + 1, w + 1), np.float64)
        ii[:, 1:, 1:] = f.cumsum(1).cumsum(2)
        return ii

    return remembered(f, "integral", table)


def read_only(a: np.ndarray) -> np.ndarray:
    """``a`` itself, marked read-only: a map that every later step only reads, whose
    summed-area table and window norms are then kept while it lives (:func:`remembered`).

    >>> read_only(np.zeros(2)).flags.writeable
    False
    """
    a.setflags(write=False)
    return a


#: What :func:`remembered` keeps: ``(id(map), what) -> value``, each entry dropped when
#: its map is freed.
_KEPT: dict[tuple[int, object], np.ndarray] = {}


def remembered(f: np.ndarray, what: object, make: Callable[[], np.ndarray]) -> np.ndarray:
    """``make()``, computed once per read-only map ``f`` and ``what`` while ``f`` lives.

    A quantity of a feature map that several steps ask for (its summed-area table, the
    norms of its windows' means) is kept beside the map and dropped with it (a weak
    reference's callback), so nothing outlives the photo's maps. A writeable ``f`` could
    change under the same identity: its value is made afresh every time. The kept value
    is marked read-only.

    Parameters
    ----------
    f : ndarray, the map (its identity is the key)
    what : hashable, which quantity (with its parameters)
    make : () -> ndarray

    Returns
    -------
    ndarray, ``make()``'s result (read-only when kept)
    """
    import weakref

    if f.flags.writeable:
        return make()
    key = (id(f), what)
    hit = _KEPT.get(key)
    if hit is not None:
        return hit
    out = make()
    out.setflags(write=False)
    _KEPT[key] = out
    weakref.finalize(f, _KEPT.pop, key, None)
    return out


def box_contrast(f: np.ndarray, boxes: np.ndarray, cell_px: float,
                 integral: np.ndarray | None = None) -> np.ndarray:
    """Centre-surround contrast of pixel boxes in a feature map.

    ``(1 - cos(m_box, m_ring)) * |m_box|``, with ``m_box`` the mean feature over the
    box's cells and ``m_ring`` that of the box grown by its own width and height on
    every side, minus the box (clipped to the map).

    Parameters
    ----------
    f : (C, h, w) float32 (:func:`rescu.extension.dense.hypercolumn`)
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the backbone input
    cell_px : pixels per cell
    integral : :func:`integral_map` of ``f`` when already computed (None: computed here)

    Returns
    -------
    (n,) float in [0, 2]
    """
    c, h, w = f.shape
    ii = integral_map(f) if integral is None else integral

    def total(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        return ii[:, y1, x1] - ii[:, y0, x1] - ii[:, y1, x0] + ii[:, y0, x0]

    out = np.zeros(len(boxes))
    for i, box in enumerate(np.asarray(boxes, float).reshape(-1, 4)):
        x0, y0, x1, y1 = box_cells(box, cell_px, h, w)
        dx, dy = x1 - x0, y1 - y0
        X0, Y0, X1, Y1 = max(0, x0 - dx), max(0, y0 - dy), min(w, x1 + dx), min(h, y1 + dy)
        inner, outer = dx * dy, (X1 - X0) * (Y1 - Y0)
        s = total(x0, y0, x1, y1)
        mc = s / inner
        mr = (total(X0, Y0, X1, Y1) - s) / (outer - inner) if outer > inner else mc
        nc, nr = np.linalg.norm(mc) + 1e-9, np.linalg.norm(mr) + 1e-9
        out[i] = (1.0 - float(mc @ mr) / (nc * nr)) * nc
    return out


def box_cells(box: Sequence[float], cell_px: float, h: int, w: int
              ) -> tuple[int, int, int, int]:
    """The cells ``[x0, x1) x [y0, y1)`` of an ``h x w`` map that a pixel box
    ``[x, y, w, h]`` touches, at least one, clipped to the map.

    >>> box_cells([4, 0, 20, 8], 8.0, 10, 10)
    (0, 0, 3, 1)
    """
    x, y, bw, bh = (float(v) for v in box)
    x0 = int(np.clip(np.floor(x / cell_px), 0, w - 1))
    y0 = int(np.clip(np.floor(y / cell_px), 0, h - 1))
    x1 = int(np.clip(np.ceil((x + bw) / cell_px), x0 + 1, w))
    y1 = int(np.clip(np.ceil((y + bh) / cell_px), y0 + 1, h))
    return x0, y0, x1, y1


def box_features(f: np.ndarray, cell_px: float, boxes: np.ndarray,
                 integral: np.ndarray | None = None) -> np.ndarray:
    """The unit mean feature of ``f`` over each box.

    Parameters
    ----------
    f : (C, h, w) float32
    cell_px : pixels per cell
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the map's input (each covers >= 1 cell)
    integral : :func:`integral_map` of ``f`` when already computed (None: computed here)

    Returns
    -------
    (n, C) float32, rows of unit norm
    """
    ii = integral_map(f) if integral is None else integral
    h, w = f.shape[1:]
    b = np.asarray(boxes, float).reshape(-1, 4)
    emb = np.zeros((len(b), f.shape[0]), np.float32)
    for i, box in enumerate(b):
        x0, y0, x1, y1 = box_cells(box, cell_px, h, w)
        v = ii[:, y1, x1] - ii[:, y0, x1] - ii[:, y1, x0] + ii[:, y0, x0]
        emb[i] = v / (np.linalg.norm(v) + 1e-12)
    return emb


def group_prototype(f: np.ndarray, cell_px: float, boxes: np.ndarray,
                    integral: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, tuple[float, float], tuple[int, int]]:
    """What a completion correlates: the unit mean of the (m >= 1) ``boxes``' features
    (:func:`box_features`), their (m,) similarities to it, their median ``(w, h)`` in
    pixels and that size in cells ``(sw, sh)`` (at least 1)."""
    b = np.asarray(boxes, float).reshape(-1, 4)
    return prototype_of(box_features(f, cell_px, b, integral), b, cell_px)


def prototype_of(emb: np.ndarray, boxes: np.ndarray, cell_px: float
                 ) -> tuple[np.ndarray, np.ndarray, tuple[float, float], tuple[int, int]]:
    """:func:`group_prototype` from the boxes' features ``emb`` (m, C) (:func:`box_features`
    of ``boxes`` (m, 4) px), for a caller that also needs the features."""
    b = np.asarray(boxes, float).reshape(-1, 4)
    proto = emb.mean(0)
    proto /= np.linalg.norm(proto) + 1e-9
    bw, bh = float(np.median(b[:, 2])), float(np.median(b[:, 3]))
    return proto, emb @ proto, (bw, bh), (max(1, int(round(bw / cell_px))),
                                          max(1, int(round(bh / cell_px))))


def map_score(f: np.ndarray, cell_px: float, boxes: np.ndarray,
              emb: np.ndarray | None = None, integral: np.ndarray | None = None,
              mean: np.ndarray | None = None) -> float:
    """How much a set of boxes stands out in a feature map, as the dense source ranks its
    groups (:func:`rescu.extension.dense.dense_candidates`, without the objectness): the
    boxes' mean centre-surround contrast (:func:`box_contrast`)
    times their rarity, ``1 - cos`` of their mean feature with the image's mean feature
    (background is what the image mostly is).

    Parameters
    ----------
    f : (C, h, w) float32
    cell_px : pixels of the map's input per cell
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the map's input
    emb : :func:`box_features` of the boxes when already computed
    integral : :func:`integral_map` of ``f`` when already computed
    mean : (C,) the image's unit mean feature (:func:`unit_mean`) when already computed

    Returns
    -------
    float in [0, 2] (0 for no boxes)

    >>> f = np.zeros((2, 8, 8), np.float32); f[0] = 1.0; f[:, 2:4, 2:4] = [[[0.0]], [[1.0]]]
    >>> round(map_score(f, 8.0, np.array([[16, 16, 16, 16]])), 3)  # a block unlike its ring
    0.933
    >>> round(map_score(f, 8.0, np.array([[48, 48, 16, 16]])), 3)  # background
    0.0
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if not len(b):
        return 0.0
    emb = box_features(f, cell_px, b, integral) if emb is None else emb
    g = unit_mean(f) if mean is None else mean
    cen = emb.mean(0)
    rarity = 1.0 - float(cen @ g) / (np.linalg.norm(cen) + 1e-12)
    return float(float(box_contrast(f, b, cell_px, integral).mean()) * rarity)


def maximum_filter(a: np.ndarray, size: int | Sequence[int]) -> np.ndarray:
    """The largest value of ``a`` in the window of ``size`` cells centred at each cell.

    Equal to ``scipy.ndimage.maximum_filter(a, size, mode="nearest")`` (a window that
    leaves the array takes the maximum of its part inside), without importing
    ``scipy.ndimage`` (0.1-0.4 s of the dense step's process): one axis at a time, the
    maximum of shifted copies.

    Parameters
    ----------
    a : (...) array, any number of axes
    size : odd int per axis (or one for every axis), >= 1

    Returns
    -------
    array of ``a``'s shape and dtype

    >>> maximum_filter(np.array([[1, 5, 2, 0], [0, 0, 0, 7]]), (1, 3)).tolist()
    [[5, 5, 5, 2], [0, 0, 7, 7]]
    """
    out = np.array(a, copy=True)
    sizes = [int(size)] * out.ndim if np.ndim(size) == 0 else [int(s) for s in size]
    if len(sizes) != out.ndim or any(s < 1 or s % 2 == 0 for s in sizes):
        raise ValueError(f"size must be odd and >= 1 per axis of a {out.ndim}-d array, "
                         f"got {size!r}")
    for axis, s in enumerate(sizes):
        r, n = s // 2, out.shape[axis]
        if r == 0 or n == 0:
            continue
        src = np.moveaxis(out, axis, 0)
        pad = np.concatenate([np.repeat(src[:1], r, 0), src, np.repeat(src[-1:], r, 0)])
        acc = src.copy()
        for k in range(2 * r + 1):
            np.maximum(acc, pad[k:k + n], out=acc)
        out = np.moveaxis(acc, 0, axis)
    return np.ascontiguousarray(out)


def unit_mean(f: np.ndarray) -> np.ndarray:
    """The mean feature of ``f`` (C, h, w) over every cell, scaled to unit norm -> (C,)."""
    g = f.reshape(f.shape[0], -1).mean(1)
    return g / (np.linalg.norm(g) + 1e-12)


OBJECT_PROBE = 1.0 / 3.0
"""The part of each box that :func:`separation` compares for RPs of whole objects: the
central third of its width and height (where two abutting objects have the gap between
them and one structure has more of itself)."""


def centre_part(boxes: np.ndarray, fraction: float, min_side: float) -> np.ndarray:
    """The central ``fraction`` of each box's width and height, at least ``min_side``
    pixels on each axis, around the box's centre.

    >>> centre_part(np.array([[0.0, 0, 30, 12]]), 1 / 3, 8.0).tolist()
    [[10.0, 2.0, 10.0, 8.0]]
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    wh = np.maximum(b[:, 2:] * float(fraction), float(min_side))
    return np.c_[b[:, :2] + b[:, 2:] / 2 - wh / 2, wh]


def _midway(a: np.ndarray, b: np.ndarray, cell_px: float) -> np.ndarray:
    """The box of their mean size half-way between each pair of boxes ``a[k]``, ``b[k]``
    ((n, 4) ``[x, y, w, h]`` each), at least one cell on each side: (n, 4)."""
    wh = (a[:, 2:] + b[:, 2:]) / 2
    centre = (a[:, :2] + a[:, 2:] / 2 + b[:, :2] + b[:, 2:] / 2) / 2
    return np.c_[centre - wh / 2, np.maximum(wh, cell_px)]


def separation(f: np.ndarray, cell_px: float, boxes: np.ndarray, proto: np.ndarray,
               sims: np.ndarray, reach: float, integral: np.ndarray | None = None,
               probe: float = 1.0) -> float | None:
    """How much less the space between neighbouring instances resembles their prototype
    than they do: whether they are separate things or samples along one structure.

    For each instance whose nearest instance (centre distance) lies within ``reach`` x
    the two boxes' mean side, the box of their mean size half-way between them is
    compared with the prototype: its *dip* is the pair's mean similarity minus the
    midpoint box's. Between two windows, two coins or two cars, the midpoint box holds
    wall, table or the edges of both, and the dip is clear; along a ledge, a board's
    frame, a cup's rim or a road marking the midpoint box holds more of the same and the
    dip is about 0 or negative.

    Pooled over a whole box, two objects that abut (parked cars, seen from above) look
    like one more object half-way between them: the midpoint box holds half of each.
    With ``probe`` < 1 only the central ``probe`` of each box's width and height is
    compared (:func:`centre_part`, at least one cell): the instances' centres with their
    own prototype, and the centre of the midpoint box, which holds the gap between the
    two objects, with it (:data:`OBJECT_PROBE` for RPs of whole objects). Along one
    structure the centre of the midpoint box still holds more of it.

    Parameters
    ----------
    f : (C, h, w) float32, feature map (unit norm per cell)
    cell_px : pixels of the map's input per cell
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the map's input
    proto : (C,) unit prototype of the instances
    sims : (n,) the instances' similarities to ``proto``
    reach : neighbours farther apart than this x their mean side are not compared
    integral : :func:`integral_map` of ``f`` when already computed
    probe : the central part of each box compared, fraction of its sides in (0, 1];
        below 1, ``proto`` and ``sims`` are those of the instances' central parts,
        computed here (the arguments are not used)

    Samples of one structure lie next to one another: nearly every one has a neighbour
    within ``reach``. When fewer than half the instances have one, the RP's instances
    are mostly apart from one another, and its few close pairs (two boxes on one object,
    its head and its base, or two objects parked close) cannot say that the whole RP
    samples one structure: no verdict.

    Returns
    -------
    The median dip in [-2, 2] over the instances with a near neighbour; None when fewer
    than two, or fewer than half the instances, have one (no evidence either way).

    >>> f = np.zeros((2, 4, 12), np.float32); f[0] = 1.0
    >>> f[:, :, 1::4] = np.array([0.0, 1.0])[:, None, None]   # objects every 4 cells
    >>> boxes = np.array([[8.0 + 32 * k, 8, 8, 8] for k in range(3)])
    >>> proto = np.array([0.0, 1.0]); sims = np.ones(3)
    >>> separation(f, 8.0, boxes, proto, sims, 5.0)          # wall between them
    1.0
    >>> f[:, 1, :] = np.array([0.0, 1.0])[:, None]            # one band through them
    >>> separation(f, 8.0, boxes, proto, sims, 5.0)
    0.0
    >>> g = np.zeros((2, 4, 12), np.float32); g[0] = 1.0       # objects 3 cells wide ...
    >>> for x0 in (0, 4, 8): g[:, :, x0:x0 + 3] = np.array([0.0, 1.0])[:, None, None]
    >>> abut = np.array([[32.0 * k, 0, 24, 24] for k in range(3)])   # ... 1-cell gaps
    >>> separation(g, 8.0, abut, proto, sims, 5.0) < 0.3          # pooled: like one more
    True
    >>> separation(g, 8.0, abut, proto, sims, 5.0, probe=1 / 3)   # its centre: the gap
    1.0
    >>> apart = np.array([[8.0, 8, 8, 8], [16, 8, 8, 8], [40, 24, 8, 8], [72, 24, 8, 8],
    ...                   [88, 0, 8, 8]])       # one close pair (in the band), three apart
    >>> separation(f, 8.0, apart, proto, np.ones(5), 2.5) is None
    True
    >>> separation(f, 8.0, apart[:3], proto, np.ones(3), 2.5)     # two of three: judged
    0.0
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if len(b) < 2:
        return None
    c = b[:, :2] + b[:, 2:] / 2
    side = np.sqrt(b[:, 2] * b[:, 3])
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    np.fill_diagonal(d, np.inf)
    j = d.argmin(1)
    near = np.where(d[np.arange(len(b)), j] < reach * (side + side[j]) / 2)[0]
    if len(near) < max(2, len(b) / 2):    # mostly apart: a few close pairs do not decide
        return None
    mid = _midway(b[near], b[j[near]], cell_px)
    s = np.asarray(sims, float)
    if probe < 1.0:
        ii = integral_map(f) if integral is None else integral
        emb = box_features(f, cell_px, centre_part(b, probe, cell_px), ii)
        proto = emb.mean(0)
        proto = proto / (np.linalg.norm(proto) + 1e-9)
        s, mid, integral = emb @ proto, centre_part(mid, probe, cell_px), ii
    m = box_features(f, cell_px, mid, integral) @ np.asarray(proto, float)
    return float(np.median((s[near] + s[j[near]]) / 2 - m))


def second_boxes(f: np.ndarray, cell_px: float, groups: Sequence[np.ndarray], reach: float,
                 floor: float, probe: float = OBJECT_PROBE,
                 integral: np.ndarray | None = None) -> list[np.ndarray]:
    """Which boxes are a second box on an object that an earlier box already holds (a
    chess piece's head and its base, a window's pane and its frame).

    Boxes are read in order: the groups (RPs, most confident first), each in its own
    order. A box is *second* when its nearest earlier box that is kept (of an earlier
    group or of its own) lies within ``reach`` x the two boxes' mean side, and the box
    half-way between them resembles the two: their mean similarity to the pair's own
    prototype, minus that of the half-way box, is below ``floor`` (the *dip* of
    :func:`separation`, for one pair, on the central ``probe`` of each box). Between two
    objects the half-way box holds the gap; between two parts of one object it holds
    more of the object. The first box on an object is kept.

    Parameters
    ----------
    f : (C, h, w) float32, feature map (unit norm per cell)
    cell_px : pixels of the map's input per cell
    groups : (n_i, 4) ``[x, y, w, h]`` arrays, pixels of the map's input
    reach : boxes farther apart than this x their mean side are not compared
    floor : a dip below this makes the later box second; -2: none is
    probe : the central part of each box compared, fraction of its sides in (0, 1]
    integral : :func:`integral_map` of ``f`` when already computed

    Returns
    -------
    one (n_i,) bool array per group, True for a second box

    >>> f = np.zeros((2, 4, 16), np.float32); f[0] = 1.0
    >>> f[:, :, 1:4] = np.array([0.0, 1.0])[:, None, None]   # one object 3 cells wide
    >>> f[:, :, 7:10] = np.array([0.0, 1.0])[:, None, None]  # another, wall between
    >>> head, base = [8.0, 0, 24, 16], [8, 16, 24, 16]       # two boxes on the first
    >>> other = [56.0, 0, 24, 32]                            # within reach of head
    >>> [g.tolist() for g in second_boxes(f, 8.0, [np.array([head, other]),
    ...                                             np.array([base])], 2.5, 0.1)]
    [[False, False], [True]]
    >>> [g.tolist() for g in second_boxes(f, 8.0, [np.array([head, other])], 2.5, 0.1)]
    [[False, False]]
    """
    ii = integral_map(f) if integral is None else integral
    flags = [np.zeros(len(np.asarray(g).reshape(-1, 4)), bool) for g in groups]
    kept = np.zeros((0, 4))
    for k, g in enumerate(groups):
        for i, b in enumerate(np.asarray(g, float).reshape(-1, 4)):
            if len(kept) and floor > -2.0:
                c, kc = b[:2] + b[2:] / 2, kept[:, :2] + kept[:, 2:] / 2
                d = np.linalg.norm(kc - c, axis=1)
                j = int(d.argmin())
                if d[j] < reach * (np.sqrt(b[2] * b[3]) + np.sqrt(kept[j, 2] * kept[j, 3])) / 2:
                    mid = _midway(b[None], kept[j:j + 1], cell_px)[0]
                    emb = box_features(f, cell_px, centre_part(
                        np.array([b, kept[j], mid]), probe, cell_px), ii)
                    proto = emb[:2].mean(0)
                    proto = proto / (np.linalg.norm(proto) + 1e-9)
                    if float(emb[:2].mean(0) @ proto - emb[2] @ proto) < floor:
                        flags[k][i] = True
                        continue
            kept = np.vstack([kept, b])
    return flags
