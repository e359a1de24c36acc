"""Whole objects from the dense source's groups: completion, extent, one RP per object.

The dense source (:mod:`rescu.extension.dense`) groups feature-map blobs that look
alike. A group holds only the blobs that were strong enough to be detected, each a
square of one of a few fixed sizes, often on one part of an object (a coin's bright
rim, a chess piece's head), and two groups often sit on two parts of the same objects.
This module turns each kept group into an RP of whole objects, the way class-agnostic
counters work once they hold a few exemplars:

1. **Completion by exemplar correlation** (:func:`complete_group`): the group's
   prototype (its blobs' mean feature) is correlated over the whole feature map with a
   window of the group's size (:func:`similarity_map`, cosine of the window's mean
   feature); the local maxima above a threshold taken from the group's own members
   (``completion_margin`` below their lower quantile, never below
   ``completion_floor``), suppressed at the instance size, are its instances. Objects
   that the blob detector missed (weaker contrast, a neighbour's ring in the way) are
   found when they look like the others.
2. **Extent** (:func:`rescu.extension.contrast_extent.refine_extent`): one scale, aspect and
   shift for all of the RP's boxes, chosen where the colour inside the boxes differs
   most from a ring around them (Fisher ratio in CIELAB, :func:`colour_contrast`;
   optionally plus the edges on the boxes' outlines, :func:`edge_contrast`): the
   classical scale selection of a blob detector, done jointly over the instances. A
   coin's box grows from its bright centre to the coin.
3. **One RP per object** (:func:`suppress_parts`): a group whose boxes lie mostly
   inside (or around) the boxes of a better-ranked RP holds parts of the same objects
   and is dropped; its boxes that lie elsewhere are not enough to make an RP.
4. **Confidence** (:func:`rp_confidence`, :func:`pattern_confidence`): a number in
   [0, 1], computed without ground truth for every RP of any source (stage I's too,
   :func:`score_patterns`), of how clearly its instances recur: how much more they
   resemble their prototype than the rest of the image does (the *gap*), how many they
   are, and how much their colour differs from their surroundings. RESCU-I reports only
   the RPs at or above ``dense.min_confidence`` (:func:`score_and_split`).

Every function works in the pixels of the backbone input (cells of ``cell_px``) or of
the image it is given; :func:`rescu.extension.dense.find_dense` converts to original
pixels.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Iterable, Sequence

import numpy as np

from ..boxes import cover_matrix, nms, touching_sides
from .boxmaps import (OBJECT_PROBE, box_features, group_prototype, integral_map, map_score,
                      maximum_filter, prototype_of, remembered, second_boxes,
                      separation)
from .contrast_extent import (colour_contrast, colour_integrals, edge_contrast, extent_score,
                     gradient_integral, rect_sums, refine_extent)

if TYPE_CHECKING:  # annotations only
    from ..discovery.sources import DenseParams


__all__ = ["similarity_map", "box_features", "complete_group", "distinctiveness",
           "whole_objects", "rp_confidence", "score_patterns",
           "colour_integrals", "rect_sums", "colour_contrast", "gradient_integral",
           "edge_contrast", "extent_score", "refine_extent",
           "suppress_parts", "pattern_confidence", "score_term", "without_parts", "on_objects",
           "one_box_applies", "one_box_per_object"]


def similarity_map(f: np.ndarray, proto: np.ndarray, side: int | tuple[int, int]
                   ) -> np.ndarray:
    """Cosine similarity of the mean feature of the ``side x side`` window centred at each
    cell with ``proto``.

    Parameters
    ----------
    f : (C, h, w) float32, feature map (unit norm per cell)
    proto : (C,) float, the prototype (any norm)
    side : window side, cells (>= 1); or ``(width, height)``

    Returns
    -------
    (h, w) float32 in [-1, 1]

    >>> f = np.zeros((2, 5, 5), np.float32); f[0] = 1; f[:, 2, 2] = [0, 1]
    >>> s = similarity_map(f, np.array([0.0, 1.0]), 1)
    >>> float(s[2, 2]), float(s[0, 0])
    (1.0, 0.0)
    """
    import cv2

    sw, sh = (side, side) if np.isscalar(side) else side   # type: ignore[misc]
    ksize = (max(1, int(sw)), max(1, int(sh)))
    p = np.asarray(proto, np.float32) / (np.linalg.norm(proto) + 1e-9)
    # the windows' means are linear in f: the prototype's side of the cosine is one
    # window sum of p . f, not one per channel
    acc = cv2.boxFilter(np.tensordot(p, f, 1).astype(np.float32, copy=False), -1, ksize,
                        normalize=True, borderType=cv2.BORDER_REFLECT)
    return acc / (window_norms(f, ksize) + 1e-9)


def window_norms(f: np.ndarray, ksize: tuple[int, int]) -> np.ndarray:
    """The norm of the mean feature of the ``ksize`` (width, height) window centred at
    each cell of ``f`` (C, h, w) (reflected at the border) -> (h, w) float32.

    The half of :func:`similarity_map` that does not depend on the prototype (one box
    filter per channel): for a read-only ``f`` (the dense source's maps) made once per
    window size while ``f`` lives (:func:`rescu.extension.boxmaps.remembered`), so that
    the completion, the turned completion and the confidence of every group on one map
    filter its channels once.
    """
    import cv2

    k = (max(1, int(ksize[0])), max(1, int(ksize[1])))

    def norms() -> np.ndarray:
        norm = np.zeros(f.shape[1:], np.float32)
        for c in range(f.shape[0]):
            m = cv2.boxFilter(f[c], -1, k, normalize=True, borderType=cv2.BORDER_REFLECT)
            norm += m * m
        return np.sqrt(norm)

    return remembered(f, ("window_norms", k), norms)


def complete_group(f: np.ndarray, cell_px: float, boxes: np.ndarray, margin: float,
                   floor: float, quantile: float = 20.0, integral: np.ndarray | None = None,
                   prototype: tuple | None = None
                   ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Every instance of an RP, by correlating its prototype over the map.

    The prototype is the mean of the instances' features (:func:`box_features`); the
    similarity map uses a window of their median width and height
    (:func:`similarity_map`); its local maxima (within 0.6 x the window) above the
    threshold, suppressed at IoU 0.2, are the instances, boxes of the median size.

    Parameters
    ----------
    f : (C, h, w) float32, unit norm per cell (:func:`rescu.extension.dense.hypercolumn`)
    cell_px : pixels of the map's input per cell
    boxes : (m, 4) ``[x, y, w, h]`` the RP's instances so far, pixels of the map's input
    margin : the threshold is the instances' ``quantile``-th percentile similarity to the
        prototype minus this
    floor : ... and never below this
    quantile : percentile of the instances' similarities, in [0, 100]
    integral : :func:`integral_map` of ``f`` when already computed
    prototype : :func:`rescu.extension.boxmaps.group_prototype` of ``boxes``, when
        already computed

    Returns
    -------
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the map's input, best similarity first
    sims : (n,) their similarity to the prototype
    tau : the threshold used
    sim : (h, w) the similarity map
    """
    proto, own, (bw, bh), (sw, sh) = (prototype if prototype is not None else
                                      group_prototype(f, cell_px, boxes, integral))
    sim = similarity_map(f, proto, (sw, sh))
    tau = max(float(floor), float(np.percentile(own, quantile)) - float(margin))
    out, sims = window_peaks(sim, (sw, sh), tau, cell_px, (bw, bh))
    keep = nms(out, sims, 0.2)
    order = keep[np.argsort(-sims[keep], kind="stable")]
    return out[order].reshape(-1, 4), sims[order], tau, sim


def window_peaks(sim: np.ndarray, window: tuple[int, int], tau: float, cell_px: float,
                 box: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Maxima of ``sim`` within 0.6 x the ``(w, h)`` cell ``window``, at least ``tau``, a
    quarter window off the border: ``box`` (w, h) px boxes (n, 4) on them, their sims."""
    (sw, sh), (bw, bh), (h, w) = window, box, sim.shape
    ry, rx = max(1, int(round(sh * 0.6))), max(1, int(round(sw * 0.6)))
    ys, xs = np.nonzero((sim == maximum_filter(sim, (2 * ry + 1, 2 * rx + 1))) & (sim >= tau))
    inside = ((ys + 0.5 >= 0.25 * sh) & (ys + 0.5 <= h - 0.25 * sh)
              & (xs + 0.5 >= 0.25 * sw) & (xs + 0.5 <= w - 0.25 * sw))
    ys, xs = ys[inside], xs[inside]
    out = np.c_[(xs + 0.5) * cell_px - bw / 2, (ys + 0.5) * cell_px - bh / 2,
                np.full(len(xs), bw), np.full(len(xs), bh)]
    return out, sim[ys, xs].astype(float)


# ----------------------------------------------------------------------------- extent
def distinctiveness(sim: np.ndarray, sims: np.ndarray, boxes: np.ndarray,
                    cell_px: float, quantile: float = 95.0, grow: float = 0.5) -> float:
    """How much more an RP's instances resemble their prototype than anything else.

    The median similarity of the instances minus the ``quantile``-th percentile of the
    similarity map over the cells away from every instance: outside each box grown by
    ``grow`` x its width and height on every side (a window there does not overlap an
    instance much). When such cells are fewer than 5 % of the map (objects that touch,
    packed fruit or logs), the margin is halved, and when that still leaves fewer, the
    cells outside the boxes themselves are used: a box that stops short of its object's
    edge leaves that object's rim outside it, which resembles the prototype, so going
    straight to no margin measured packed objects against their own rims and not the
    gaps between them. A pattern of texture or background (found everywhere) scores
    about 0 or less, a set of distinct objects clearly more.

    Parameters
    ----------
    sim : (h, w) similarity map (:func:`similarity_map`)
    sims : (n,) the instances' similarities
    boxes : (n, 4) the instances' boxes, pixels of the map's input
    cell_px : pixels per cell
    quantile : percentile of the other cells, in [0, 100]
    grow : margin around each box, fraction of its side

    Returns
    -------
    float in [-2, 2]; -1.0 when no cell is outside the boxes
    """
    h, w = sim.shape
    b = np.asarray(boxes, float).reshape(-1, 4)

    def free_cells(g: float) -> np.ndarray:
        free = np.ones(sim.shape, bool)
        for x, y, bw, bh in b:
            x0 = max(0, int(np.floor((x - g * bw) / cell_px)))
            y0 = max(0, int(np.floor((y - g * bh) / cell_px)))
            x1 = min(w, int(np.ceil((x + (1 + g) * bw) / cell_px)))
            y1 = min(h, int(np.ceil((y + (1 + g) * bh) / cell_px)))
            free[y0:y1, x0:x1] = False
        return free

    free = free_cells(grow)
    for g in (grow / 2, 0.0):
        if free.mean() >= 0.05:
            break
        free = free_cells(g)
    if not free.any() or not len(sims):
        return -1.0
    return float(np.median(sims) - np.percentile(sim[free], quantile))


def rp_confidence(f: np.ndarray, cell_px: float, s: float, boxes: np.ndarray,
                  integrals: tuple[np.ndarray, np.ndarray], params: DenseParams,
                  objects: bool = True, integral: np.ndarray | None = None
                  ) -> dict[str, float]:
    """The confidence of any RP (from any source) from its instance boxes.

    The instances' mean features over their boxes give the prototype; the similarity map
    at the median box size (:func:`similarity_map`) and :func:`distinctiveness` give the
    gap; :func:`pattern_confidence` combines it with the number of instances.

    Parameters
    ----------
    f : (C, h, w) float32, the feature map of the image resized by ``s``
    cell_px : pixels of the backbone input per cell
    s : backbone-input pixels per pixel of ``boxes``
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the image of ``integrals``
    integrals : :func:`colour_integrals` of that image
    params : :class:`rescu.discovery.sources.DenseParams` (``confidence_*`` scales)
    objects : whether the boxes have the extent of objects (the dense RPs). False for
        stage I's keypoint boxes (:func:`score_patterns`): the colour contrast is
        reported but not counted, and the confidence is multiplied by the *resolution*
        ``min(1, side / (2 cell_px))**2``, ``side`` the median of the boxes' shorter
        sides in backbone-input pixels: the map's coarser half has a stride of two
        cells, so it cannot tell whether boxes smaller than that look alike, nor boxes
        thinner than that (a sliver along an edge, whose features are mostly those of
        what lies beside it), however long (their gap is measured on
        the boxes themselves, where a dense RP's was measured on its blobs, at least
        that size, before its extent was refined). Such an RP also gets its *map score*
        (:func:`map_score`: its boxes' centre-surround contrast in ``f`` x their rarity,
        the dense source's ranking score without the objectness), which multiplies its
        confidence by :func:`score_term` with ``params.confidence_stage1_score_scale``
        (0: not counted), as a dense RP's ranking score does, and its *separation*
        (:func:`separation` with ``params.separation_reach``, when defined), which
        :func:`rescu.discovery.sources.split_by_confidence` compares with
        ``params.min_separation``. With ``objects``, the *separation* is measured on
        the boxes' central thirds (``probe`` :data:`rescu.extension.boxmaps.OBJECT_PROBE`:
        pooled over whole boxes, objects that abut look like one more object half-way
        between them), for ``params.min_object_separation``
    integral : :func:`integral_map` of ``f`` when already computed

    Returns
    -------
    ``{"confidence": float in [0, 1], "gap": float, "contrast": float}``, and
    ``"resolution"`` and ``"map_score"`` when not ``objects``, and ``"separation"`` when
    defined
    """
    b = np.asarray(boxes, float).reshape(-1, 4) * s
    if len(b) < 2:
        return {"confidence": 0.0, "gap": -1.0, "contrast": 0.0}
    emb = box_features(f, cell_px, b, integral)
    proto, sims, _, side = prototype_of(emb, b, cell_px)  # sims: the instances' similarities
    gap = distinctiveness(similarity_map(f, proto, side), sims, b, cell_px)
    con = float(np.median(colour_contrast(integrals, np.asarray(boxes, float).reshape(-1, 4))))
    conf = pattern_confidence(gap, len(b), con if objects else None,
                              params.confidence_gap_scale, params.confidence_n_scale,
                              params.confidence_contrast_scale)
    out = {"gap": round(gap, 4), "contrast": round(con, 4)}
    if not objects:
        side = float(np.median(np.minimum(b[:, 2], b[:, 3])))  # the shorter side
        out["resolution"] = round(min(1.0, side / (2.0 * cell_px)) ** 2, 4)
        out["map_score"] = round(map_score(f, cell_px, b, emb, integral), 4)
        conf *= out["resolution"] * score_term(out["map_score"],
                                               params.confidence_stage1_score_scale)
    sep = separation(f, cell_px, b, proto, sims, params.separation_reach, integral,
                     probe=OBJECT_PROBE if objects else 1.0)
    if sep is not None:
        out["separation"] = round(sep, 4)
    return {"confidence": round(conf, 4), **out}


# ------------------------------------------------------------------------- selection
def suppress_parts(ranked: Sequence[np.ndarray], cover: float, min_instances: int,
                   max_patterns: int) -> list[np.ndarray]:
    """One RP per object: the first ``max_patterns`` box sets of ``ranked`` (best first)
    that do not hold parts of a better one's objects.

    A box *overlaps* a kept RP when it lies inside one of its boxes, or one of them inside
    it, by more than ``cover`` of the smaller (:func:`rescu.boxes.cover_matrix`).
    A set whose boxes mostly overlap is dropped; otherwise its overlapping boxes are
    removed, and it is kept when ``min_instances`` remain.

    Parameters
    ----------
    ranked : list of (n_i, 4) ``[x, y, w, h]`` arrays, best first
    cover : in (0, 1]
    min_instances : least boxes of a kept set
    max_patterns : most sets kept

    Returns
    -------
    list of (m_i, 4) arrays, in the order of ``ranked``

    >>> a = np.array([[0, 0, 10, 10], [20, 0, 10, 10], [40, 0, 10, 10]], float)
    >>> parts = a * [1, 1, 0.5, 0.5] + [2, 2, 0, 0]
    >>> [len(k) for k in suppress_parts([a, parts, a + [0, 50, 0, 0]], 0.5, 2, 3)]
    [3, 3]
    """
    kept: list[np.ndarray] = []
    taken = np.zeros((0, 4))
    for boxes in ranked:
        b = without_parts(np.asarray(boxes, float).reshape(-1, 4), taken, cover,
                          min_instances)
        if b is None:
            continue
        kept.append(b)
        taken = np.vstack([taken, b])
        if len(kept) >= max_patterns:
            break
    return kept


def without_parts(boxes: np.ndarray, taken: np.ndarray, cover: float, min_instances: int
                  ) -> np.ndarray | None:
    """``boxes`` less those on the objects of ``taken`` (:func:`suppress_parts`' rule), or
    None when most of them are (the set holds parts of those objects) or fewer than
    ``min_instances`` remain.

    >>> kept = np.array([[0, 0, 10, 10]], float)
    >>> without_parts(np.array([[2, 2, 5, 5], [30, 0, 10, 10], [50, 0, 10, 10]], float),
    ...               kept, 0.5, 2).tolist()
    [[30.0, 0.0, 10.0, 10.0], [50.0, 0.0, 10.0, 10.0]]
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    dup = on_objects(b, taken, cover)
    if len(b) and dup.mean() > 0.5:
        return None
    b = b[~dup]
    return b if len(b) >= min_instances else None


def on_objects(boxes: np.ndarray, taken: np.ndarray, cover: float) -> np.ndarray:
    """Which of ``boxes`` lie on an object of ``taken``: inside one of its boxes, or one
    of them inside it, by more than ``cover`` of the smaller
    (:func:`rescu.boxes.cover_matrix`).

    Parameters
    ----------
    boxes, taken : (n, 4) and (m, 4) ``[x, y, w, h]``, one pixel unit
    cover : in (0, 1]

    Returns
    -------
    (n,) bool

    >>> on_objects(np.array([[2, 2, 5, 5], [30, 0, 10, 10]], float),
    ...            np.array([[0, 0, 10, 10]], float), 0.5).tolist()
    [True, False]
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    t = np.asarray(taken, float).reshape(-1, 4)
    if not len(t) or not len(b):
        return np.zeros(len(b), bool)
    return (cover_matrix(b, t).max(1) > cover) | (cover_matrix(t, b).max(0) > cover)


def pattern_confidence(gap: float, n: int, contrast: float | None, gap_scale: float,
                       n_scale: float, contrast_scale: float, score: float | None = None,
                       score_scale: float = 0.0) -> float:
    """How clearly an RP recurs, in [0, 1], without ground truth.

    The product of saturating terms ``1 - exp(-x / scale)``:

    * the *gap* (:func:`distinctiveness`): how much more the instances resemble their
      prototype than anything else in the image does. A pattern that is everywhere
      (texture, background) or that its own instances barely share has none;
    * ``n - 1``, the number of instances beyond the first: two make a weak pattern,
      ten a clear one;
    * the instances' median colour *contrast* with their surroundings
      (:func:`colour_contrast`): objects stand out from what surrounds them, the
      gaps between objects and patches of texture do not. ``None``: not counted (the
      boxes are keypoint patches, not objects);
    * with ``score_scale`` > 0, the group's ranking *score* in the dense source
      (:class:`rescu.extension.dense.DenseCandidate`: how much its blobs stand out from
      their ring in the feature map x how unlike the image's mean feature they are x the
      ImageNet classifier's confidence on their crops). The confidence's other terms do
      not see these: a few patches of fur or background that recur more clearly than
      anything else around them have a gap and a contrast like a small real pattern's,
      but barely stand out in the map. ``None``: not counted (stage I's RPs).

    >>> round(pattern_confidence(0.3, 12, 2.0, 0.15, 3.0, 0.5), 3)
    0.827
    >>> pattern_confidence(-0.1, 12, 2.0, 0.15, 3.0, 0.5)
    0.0
    >>> round(pattern_confidence(0.3, 12, None, 0.15, 3.0, 0.5), 3)
    0.843
    >>> round(pattern_confidence(0.3, 12, 2.0, 0.15, 3.0, 0.5, score=0.01, score_scale=0.02), 3)
    0.325
    """
    g = 1.0 - np.exp(-max(float(gap), 0.0) / gap_scale)
    k = 1.0 - np.exp(-max(int(n) - 1, 0) / n_scale)
    c = 1.0 if contrast is None else 1.0 - np.exp(-max(float(contrast), 0.0) / contrast_scale)
    r = 1.0 if score is None else score_term(score, score_scale)
    return float(g * k * c * r)


def score_term(score: float, scale: float) -> float:
    """The ranking-score term of :func:`pattern_confidence`, ``1 - exp(-score / scale)``
    in [0, 1]; 1 when ``scale`` is 0 (not counted).

    >>> score_term(0.05, 0.0), round(score_term(0.03, 0.03), 3)
    (1.0, 0.632)
    """
    if not scale > 0:
        return 1.0
    return float(1.0 - np.exp(-max(float(score), 0.0) / scale))


def whole_objects(levels: Sequence[tuple[np.ndarray, float]], cell_px: float,
                  rgb: np.ndarray, ranked: Iterable[Any], params: DenseParams,
                  turned: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None
                  ) -> list[tuple[float, np.ndarray, dict[str, Any]]]:
    """RPs of whole objects from the dense source's ranked groups (steps 1-4 of the
    module docstring), each group on the map it was found on.

    A group whose objects are too small to be judged is skipped: their median side must
    span ``params.min_map_px`` pixels of its map's input (one cell of the stride-16
    half: pooled over less, a box's features are those of what surrounds it; the group
    was judged alike on blobs of at least four stride-8 cells around its objects) and
    ``params.min_object_px`` pixels of the prepared image (enlarging an image adds no
    detail: a few pixels of highlight stay a few pixels). A group that sits on the objects
    of an RP already kept (most of its boxes, :func:`on_objects`) replaces that RP when
    it is more confident (:func:`rp_confidence`; typically the same objects seen whole on
    the coarse map and in parts on the fine one), else it is skipped. A group with a few
    boxes on kept RPs' objects shares those objects with them: the more confident keeps
    them (the other loses those boxes, and is dropped when fewer than
    ``params.min_instances`` remain).

    Parameters
    ----------
    levels : list of ``(f, s)`` (:func:`rescu.extension.dense.dense_levels`): ``f``
        (C, h, w) float32, the feature map of ``rgb`` resized by ``s``
    cell_px : pixels of the backbone input per cell (8)
    rgb : (H, W, 3) uint8, the prepared image
    ranked : :class:`rescu.extension.dense.DenseCandidate` iterable, best first (with
        ``emb`` and ``level``); read only until ``params.max_patterns`` RPs at or
        above ``params.min_confidence`` (as reported, the ranking score counted) are kept
        (:func:`rescu.extension.dense.iter_level_candidates` classifies no more groups)
    params : :class:`rescu.discovery.sources.DenseParams`
    turned : callable or None
        With ``params.completion_turn``, ``(level, boxes, integral) -> (boxes,
        is_turned)``, the completion that also finds the objects lying the other way
        (:func:`rescu.extension.turned.complete_turned`); None: not looked for.

    Returns
    -------
    list of ``(score, boxes, info)``, best first, at most ``params.max_patterns``, those
    at or above ``params.min_confidence`` first (then the best-ranked below it): boxes
    (n, 4) ``[x, y, w, h]`` in pixels of ``rgb``, n >= ``params.min_instances``; info
    ``{"confidence", "gap", "contrast", "seeds", "extent", "level"}``
    (:func:`pattern_confidence`, the number of blobs the group started from, the
    transform of :func:`refine_extent`, the map)
    """
    integrals = colour_integrals(rgb)
    gradients = gradient_integral(rgb) if params.extent and params.extent_edges > 0 else None
    maps = _Integrals(levels)        # each map's summed-area table, made once when needed
    out: list[tuple[float, np.ndarray, dict[str, Any]]] = []
    for c in ranked:
        level = int(getattr(c, "level", 0))
        f, s = levels[level]
        ii = maps[level]
        boxes = np.asarray(c.boxes, float)               # the group's blobs, map pixels
        is_turned = None
        if params.complete and len(boxes):
            if turned is not None and params.completion_turn:
                boxes, is_turned = turned(level, boxes, ii)
            else:
                boxes = complete_group(f, cell_px, boxes, params.completion_margin,
                                       params.completion_floor, integral=ii)[0]
        b = boxes / s
        t: tuple[float, float, float, float] = (1.0, 1.0, 0.0, 0.0)
        if params.extent and len(b):
            b, t = refine_extent(rgb, b, params.extent_scales, params.extent_aspects,
                                 params.extent_shifts, integrals, params.extent_turn,
                                 is_turned, ring=params.extent_ring,
                                 edges=params.extent_edges, gradients=gradients)
            # two instances on one object (two parts) become one box at the object's extent
            b = b[np.sort(nms(b, extent_score(integrals, b, params.extent_ring, gradients,
                                              params.extent_edges), 0.5))]
        boxes = b * s
        if len(boxes) < params.min_instances:
            continue
        if float(touching_sides(boxes, params.touch_tolerance).mean()) > params.max_touching:
            continue
        b = _clip(boxes / s, rgb.shape[1], rgb.shape[0])
        side = float(np.median(np.sqrt(b[:, 2] * b[:, 3])))
        if side < params.min_object_px or side * s < params.min_map_px:
            continue
        extra = {"seeds": int(len(c.boxes)), "extent": [float(v) for v in t], "level": level}
        # which of these boxes lie on each kept RP's objects; a kept RP is a rival when
        # most do (when a few do, the more confident of the two keeps those, below)
        hits = [on_objects(b, kb, params.part_cover) for _, kb, _ in out]
        rivals = [k for k, h in enumerate(hits) if h.mean() > 0.5]
        if rivals:
            # the same objects as a kept RP (often the other map's view of them: parts
            # on the fine map, whole objects on the coarse one): the more confident wins
            info = rp_confidence(f, cell_px, s, b, integrals, params, integral=ii)
            if not _wins((c.score, b, info), [out[k] for k in rivals], params):
                continue
            out = [o for k, o in enumerate(out) if k not in rivals]
            hits = [h for k, h in enumerate(hits) if k not in rivals]
        taken = np.vstack([o[1] for o in out] + [np.zeros((0, 4))])    # the kept RPs' boxes
        kept = without_parts(b, taken, params.part_cover, params.min_instances)
        whole = info if rivals else None                # the confidence of all of b
        if kept is None or len(kept) < len(b):
            # a few of its boxes lie on kept RPs' objects: the more confident keeps them
            share = [k for k, h in enumerate(hits) if h.any()]
            if share:
                whole = whole or rp_confidence(f, cell_px, s, b, integrals, params,
                                               integral=ii)
                if _wins((c.score, b, whole), [out[k] for k in share], params):
                    out = _give_up_objects(out, share, b, levels, cell_px, integrals, params,
                                           maps)
                    kept = b
        if kept is None:
            continue
        info = whole if whole is not None and len(kept) == len(b) else \
            rp_confidence(f, cell_px, s, kept, integrals, params, integral=ii)
        out.append((float(c.score), kept, {**info, **extra}))
        # only an RP that will be reported fills the budget: a group below
        # min_confidence does not stop the search for clearer ones further down the
        # ranking (small cars ranked under a few faint groups of road marks)
        if sum(_reported(o, params) for o in out) >= params.max_patterns:
            break
    # at most max_patterns in all: the reportable ones, then the best-ranked others
    weak = [o for o in out if not _reported(o, params)]
    out = [o for o in out if _reported(o, params)]
    out += weak[:max(0, params.max_patterns - len(out))]
    out.sort(key=lambda o: -o[0])
    # the ranking score counts in the reported confidence, not in the choices above: it
    # is a score within one map, and the fine map's parts outscore the coarse map's
    # whole objects
    return [(sc, kb, {**info, "confidence": _reported_confidence((sc, kb, info), params)})
            for sc, kb, info in out]


def _wins(new: tuple[float, np.ndarray, dict[str, Any]],
          kept: Sequence[tuple[float, np.ndarray, dict[str, Any]]], params: DenseParams) -> bool:
    """Whether a group of :func:`whole_objects` (``(score, boxes, info)``) takes the
    objects it shares with the kept RPs ``kept``: when it is more confident than each of
    them (the confidences without the ranking score, which compares groups within one
    map only), and unless it would not be reported while one of them would
    (:func:`_reported`): objects seen clearly as a reported RP are not handed to one
    that is not shown (a group of parts, confident without its ranking score, which then
    leaves the objects with no RP)."""
    if new[2]["confidence"] <= max(o[2]["confidence"] for o in kept):
        return False
    return _reported(new, params) or not any(_reported(o, params) for o in kept)


def _reported_confidence(o: tuple[float, np.ndarray, dict[str, Any]], params: DenseParams) -> float:
    """The confidence a kept RP of :func:`whole_objects` (``(score, boxes, info)``) is
    reported with: its confidence x its ranking-score term (:func:`score_term`), 4
    decimals."""
    return round(o[2]["confidence"] * score_term(o[0], params.confidence_score_scale), 4)


def _reported(o: tuple[float, np.ndarray, dict[str, Any]], params: DenseParams) -> bool:
    """Whether a kept RP of :func:`whole_objects` reaches ``params.min_confidence`` with
    the confidence it is reported with (:func:`_reported_confidence`)."""
    return _reported_confidence(o, params) >= params.min_confidence


def _give_up_objects(out: list[tuple[float, np.ndarray, dict[str, Any]]], share: list[int],
                     b: np.ndarray, levels: Sequence[tuple[np.ndarray, float]],
                     cell_px: float, integrals: tuple[np.ndarray, np.ndarray], params: DenseParams,
                     maps: "_Integrals | None" = None
                     ) -> list[tuple[float, np.ndarray, dict[str, Any]]]:
    """The kept RPs of :func:`whole_objects` (``out``) once those at positions ``share``
    have given the objects of ``b`` ((n, 4) prepared-image pixels) to a more confident
    RP: their boxes on those objects (:func:`on_objects`) removed, their confidence
    measured again on the rest (on their own map), and dropped when fewer than
    ``params.min_instances`` remain (``maps``: the maps' summed-area tables, when
    already made)."""
    maps = _Integrals(levels) if maps is None else maps
    kept = []
    for k, (score, kb, info) in enumerate(out):
        if k in share:
            kb = kb[~on_objects(kb, b, params.part_cover)]
            if len(kb) < params.min_instances:
                continue
            lv = int(info.get("level", 0))
            fo, so = levels[lv]
            info = {**info, **rp_confidence(fo, cell_px, so, kb, integrals, params,
                                            integral=maps[lv])}
        kept.append((score, kb, info))
    return kept


class _Integrals:
    """The summed-area table (:func:`integral_map`) of each map of ``levels``
    (``[(f, s), ...]``), made on first use and kept: :func:`whole_objects` measures many
    groups on the same one or two maps."""

    def __init__(self, levels: Sequence[tuple[np.ndarray, float]]) -> None:
        self.levels = levels
        self.done: dict[int, np.ndarray] = {}

    def __getitem__(self, level: int) -> np.ndarray:
        if level not in self.done:
            self.done[level] = integral_map(self.levels[level][0])
        return self.done[level]


def _clip(b: np.ndarray, width: int, height: int) -> np.ndarray:
    """Boxes ``[x, y, w, h]`` clipped to a ``width x height`` image."""
    x0, y0 = np.clip(b[:, 0], 0, width), np.clip(b[:, 1], 0, height)
    x1 = np.clip(b[:, 0] + b[:, 2], 0, width)
    y1 = np.clip(b[:, 1] + b[:, 3], 0, height)
    return np.c_[x0, y0, x1 - x0, y1 - y0]


def score_patterns(rgb: np.ndarray, patterns: Sequence[Any], scale_factor: float,
                   params: DenseParams, f: np.ndarray, s: float) -> None:
    """Give every pattern without one a confidence (:func:`rp_confidence`), in place.

    For the RPs of stage I (the dense source's RPs carry theirs): the frozen backbone's
    map of the prepared image (:func:`rescu.extension.dense.dense_map`) and each RP's
    instance boxes; ``extra["confidence"]`` and
    ``extra["gap"]``, ``extra["contrast"]``, ``extra["resolution"]`` are set. Their
    confidence counts the gap, the number of instances and the map's resolution at
    their size (:func:`rp_confidence` with ``objects=False``), not the colour contrast:
    stage I's boxes are keypoint patches, often on a part of an object, whose colour
    hardly differs from the rest of the object around them (a textured object's does not
    at any extent), and the URP search has already checked that they recur in a
    consistent layout.

    Parameters
    ----------
    rgb : (H, W, 3) uint8, the prepared image
    patterns : list of :class:`rescu.types.Pattern`, instances in original pixels
    scale_factor : processed = original x scale_factor
    params : :class:`rescu.discovery.sources.DenseParams`
    f : (C, h, w) float32, the map of ``rgb`` resized by ``s`` (:func:`rescu.extension.dense.dense_map`)
    s : backbone-input pixels per pixel of ``rgb``
    """
    todo = [p for p in patterns if "confidence" not in p.extra]
    if not todo:
        return
    integrals = colour_integrals(rgb)
    ii = integral_map(f)
    for p in todo:
        b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4) * float(scale_factor)
        p.extra.update(rp_confidence(f, 8.0, s, b, integrals, params, objects=False,
                                     integral=ii))


def one_box_applies(params: DenseParams) -> bool:
    """Whether :func:`one_box_per_object` acts under ``params`` (DenseParams): mode
    ``objects`` and ``min_object_separation`` set (not None) and above -2, the bottom of
    its range, below which no separation falls (callers skip making or reading the map
    otherwise)."""
    sep = params.min_object_separation
    return params.mode == "objects" and sep is not None and sep > -2.0


def one_box_per_object(res: Any, fmap: tuple[np.ndarray, float], scale_factor: float,
                       params: DenseParams) -> None:
    """Drop the reported instances of ``res`` that are a second box on an object an
    earlier one holds (RPs most confident first, as reported; each in its own order),
    in place: :func:`rescu.extension.boxmaps.second_boxes` at ``params.separation_reach``
    and ``params.min_object_separation`` on the central thirds of the boxes, then
    :func:`rescu.discovery.sources.drop_second_boxes`. RESCU-I after its split, and
    RESCU-II after stage II has added its instances. Nothing unless ``params.mode`` is
    ``objects`` and ``params.min_object_separation`` set and > -2 (:func:`one_box_applies`).

    Parameters
    ----------
    res : :class:`rescu.types.ImageResult` (instances in original pixels)
    fmap : :func:`rescu.extension.dense.dense_map` of the prepared image ``(f (C, h, w), s)``
    scale_factor : prepared pixels per original pixel
    params : :class:`rescu.discovery.sources.DenseParams`
    """
    from ..discovery.sources import drop_second_boxes

    if not res.patterns or not one_box_applies(params):
        return
    k = float(scale_factor) * fmap[1]                 # original px -> map input px
    groups = [np.array([i.bbox for i in p.instances], float).reshape(-1, 4) * k
              for p in res.patterns]
    drop_second_boxes(res, second_boxes(fmap[0], 8.0, groups, params.separation_reach,
                                        params.min_object_separation), params)


def one_box_after_stage2(res: Any, s1: Any, dense: DenseParams | None,
                         scale_factor: float,
                         get_map: Callable[[DenseParams], tuple[np.ndarray, float] | None]) -> Any:
    """RESCU-II's result ``res`` with one box per object, as RESCU-I's
    (:func:`one_box_per_object`), in place; the one rule of both drivers
    (:func:`rescu.core.run`, which makes the map, and the pipeline's prediction step,
    which reads the dense step's).

    Nothing without the dense source (``dense`` None), after a failed dense step
    (``s1``'s ``extra["dense_failure"]``: there is no map), when
    :func:`one_box_applies` says no (the map is then not asked for) or when ``get_map``
    gives None (a map that cannot be read: stage II's instances are all kept).

    Parameters
    ----------
    res, s1 : :class:`rescu.types.ImageResult`, RESCU-II's and the stage-I result it
        extends
    dense : the ``dense`` parameters, or None
    scale_factor : prepared pixels per original pixel
    get_map : DenseParams -> :func:`rescu.extension.dense.dense_map` of the prepared
        image, or None

    Returns
    -------
    ``res``
    """
    if dense is None or s1.extra.get("dense_failure"):
        return res
    if one_box_applies(dense):
        fmap = get_map(dense)
        if fmap is not None:
            one_box_per_object(res, fmap, scale_factor, dense)
    return res
