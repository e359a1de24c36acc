"""Box geometry on the ground floor: overlap matrices, size gate, suppression.

Every stage and the evaluation compare axis-aligned boxes the same way; this module holds
those comparisons once and depends on nothing of the package, so the stages measure an
overlap without reaching up to :mod:`rescu.evaluation`, which builds on them.

Boxes are ``[x, y, w, h]`` in pixels (top-left corner, width, height), stacked as
``(n, 4)`` float arrays, except :func:`iou_matrix_xyxy`, whose boxes are corners
``[x0, y0, x1, y1]``. A box of zero area overlaps nothing (its ratios are 0).

* :func:`iou_matrix` - intersection over union;
* :func:`iod_matrix` - intersection over the *detection's* area (the evaluation's IOD);
* :func:`cover_matrix` - intersection over the *smaller* area (1 when one box lies in
  the other; how parts of one object are told);
* :func:`centre_in`, :func:`size_gate` - containment of centres, similar sizes;
* :func:`touching_sides` - boxes that abut with no gap (a tiling);
* :func:`greedy_keep`, :func:`nms`, :func:`suppress` - greedy suppression.
"""

from __future__ import annotations

import numpy as np

__all__ = ["intersection", "iou_matrix", "iod_matrix", "cover_matrix", "iou_matrix_xyxy",
           "centre_in", "size_gate", "touching_sides", "greedy_keep", "nms", "suppress"]


def _boxes(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, float).reshape(-1, 4)


def intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Area of the intersection of every box of ``a`` with every box of ``b``.

    Parameters
    ----------
    a : (A, 4) float
        Boxes ``[x, y, w, h]``, pixels.
    b : (B, 4) float
        Boxes ``[x, y, w, h]``, pixels.

    Returns
    -------
    (A, B) float
        Intersection areas, square pixels; 0 where the boxes are apart.

    >>> intersection(np.array([[0, 0, 10, 10]]), np.array([[5, 5, 10, 10], [20, 0, 5, 5]]))
    array([[25.,  0.]])
    """
    a, b = _boxes(a), _boxes(b)
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 0] + a[:, None, 2], b[None, :, 0] + b[None, :, 2])
    y1 = np.minimum(a[:, None, 1] + a[:, None, 3], b[None, :, 1] + b[None, :, 3])
    return np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union between every box of ``a`` and every box of ``b``.

    Parameters
    ----------
    a : (A, 4) float
        Boxes ``[x, y, w, h]``, pixels.
    b : (B, 4) float
        Boxes ``[x, y, w, h]``, pixels.

    Returns
    -------
    (A, B) float
        IoU in [0, 1]; 0 where the union is empty.

    >>> iou_matrix(np.array([[0, 0, 10, 10]]), np.array([[5, 0, 10, 10], [0, 0, 10, 10]]))
    array([[0.33333333, 1.        ]])
    """
    a, b = _boxes(a), _boxes(b)
    inter = intersection(a, b)
    union = (a[:, 2] * a[:, 3])[:, None] + (b[:, 2] * b[:, 3])[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def iod_matrix(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Intersection over detection (IOD) between every detected and ground-truth box.

    Parameters
    ----------
    det : (D, 4) float
        Detected boxes ``[x, y, w, h]``, pixels.
    gt : (G, 4) float
        Ground-truth boxes ``[x, y, w, h]``, pixels.

    Returns
    -------
    (D, G) float
        area(det ∩ gt) / area(det) in [0, 1]; 0 for a detection of zero area.

    >>> iod_matrix(np.array([[0, 0, 10, 10]]), np.array([[0, 0, 20, 20], [5, 0, 10, 10]]))
    array([[1. , 0.5]])
    """
    det, gt = _boxes(det), _boxes(gt)
    inter = intersection(det, gt)
    area = (det[:, 2] * det[:, 3])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(area > 0, inter / np.where(area > 0, area, 1.0), 0.0)
    return out


def cover_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over the smaller box's area between every box of ``a`` and ``b``.

    Parameters
    ----------
    a : (A, 4) float
        Boxes ``[x, y, w, h]``, pixels.
    b : (B, 4) float
        Boxes ``[x, y, w, h]``, pixels.

    Returns
    -------
    (A, B) float
        In [0, 1]; 1 when one box lies inside the other, 0 when either has zero area.

    >>> cover_matrix(np.array([[2, 2, 4, 4]]), np.array([[0, 0, 10, 10], [4, 2, 8, 8]]))
    array([[1. , 0.5]])
    """
    a, b = _boxes(a), _boxes(b)
    inter = intersection(a, b)
    m = np.minimum((a[:, 2] * a[:, 3])[:, None], (b[:, 2] * b[:, 3])[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(m > 0, inter / np.where(m > 0, m, 1.0), 0.0)


def iou_matrix_xyxy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes given by their corners, each side counted at least 1 pixel long.

    Stage I's search compares the bounding boxes of feature-point sets with it; a set on
    one row or column has a box of zero height or width, which the 1-pixel floor keeps
    comparable.

    Parameters
    ----------
    a : (A, 4) float
        Boxes ``[x0, y0, x1, y1]``, pixels.
    b : (B, 4) float
        Boxes ``[x0, y0, x1, y1]``, pixels.

    Returns
    -------
    (A, B) float
        IoU in [0, 1].

    >>> iou_matrix_xyxy(np.array([0., 0, 10, 10]), np.array([[0., 0, 10, 5], [0, 20, 10, 20]]))
    array([[0.5, 0. ]])
    """
    a = a.reshape(-1, 4)
    b = b.reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    area = lambda z: np.maximum(z[:, 2] - z[:, 0], 1.0) * np.maximum(z[:, 3] - z[:, 1], 1.0)  # noqa: E731
    return inter / (area(a)[:, None] + area(b)[None, :] - inter)


def centre_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether the centre of ``a_i`` lies inside ``b_j`` or the centre of ``b_j`` inside
    ``a_i`` (borders included).

    Parameters
    ----------
    a : (A, 4) float
        Boxes ``[x, y, w, h]``, pixels.
    b : (B, 4) float
        Boxes ``[x, y, w, h]``, pixels.

    Returns
    -------
    (A, B) bool

    >>> centre_in(np.array([[0, 0, 10, 10]]), np.array([[4, 4, 30, 30], [20, 0, 4, 4]]))
    array([[ True, False]])
    """
    a, b = _boxes(a), _boxes(b)

    def inside(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        c = p[:, :2] + p[:, 2:] / 2
        return ((c[:, None, 0] >= q[None, :, 0]) & (c[:, None, 0] <= q[None, :, 0] + q[None, :, 2])
                & (c[:, None, 1] >= q[None, :, 1]) & (c[:, None, 1] <= q[None, :, 1] + q[None, :, 3]))

    return inside(a, b) | inside(b, a).T


def size_gate(boxes: np.ndarray, inst: np.ndarray, tol: float) -> np.ndarray:
    """Whether each box has the size of some instance, within a factor ``tol``.

    Per instance (not against a mean size), so RPs of mixed sizes keep all their sizes.

    Parameters
    ----------
    boxes : (P, 4) float
        Candidate boxes ``[x, y, w, h]``, pixels.
    inst : (N, 4) float
        Instance boxes ``[x, y, w, h]``, pixels.
    tol : float
        Largest ratio of widths and of heights, >= 1.

    Returns
    -------
    (P,) bool
        Width and height both within ``[1/tol, tol]`` times those of one instance.

    >>> size_gate(np.array([[0, 0, 12, 9], [0, 0, 30, 10]]), np.array([[50, 50, 10, 10]]), 1.5)
    array([ True, False])
    """
    b = np.asarray(boxes, float).reshape(-1, 1, 4)
    i = np.asarray(inst, float).reshape(1, -1, 4)
    rw = b[..., 2] / np.maximum(i[..., 2], 1e-9)
    rh = b[..., 3] / np.maximum(i[..., 3], 1e-9)
    return ((rw <= tol) & (rw >= 1 / tol) & (rh <= tol) & (rh >= 1 / tol)).any(1)


def touching_sides(boxes: np.ndarray, tolerance: float) -> np.ndarray:
    """On how many of its four sides each box abuts another box of the set.

    A box abuts another on its right (left, below, above) when the other's centre lies
    one median box width (height) to the right (...) within ``tolerance`` x the median
    width and height on each axis: the boxes tile the plane there, with no gap.

    Parameters
    ----------
    boxes : (n, 4) ``[x, y, w, h]``, any pixel unit
    tolerance : fraction of the median box side, in (0, 0.5)

    Returns
    -------
    (n,) float in {0, 1, 2, 3, 4}

    >>> touching_sides(np.array([[0, 0, 10, 10], [10, 0, 10, 10], [40, 0, 10, 10]]), 0.35)
    array([1., 1., 0.])
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if len(b) < 2:
        return np.zeros(len(b))
    side = np.maximum(np.median(b[:, 2:], axis=0), 1e-9)
    c = b[:, :2] + b[:, 2:] / 2
    d = (c[None, :, :] - c[:, None, :]) / side          # (n, n, 2) in box sides
    out = np.zeros(len(b))
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        out += ((np.abs(d[..., 0] - dx) < tolerance)
                & (np.abs(d[..., 1] - dy) < tolerance)).any(axis=1)
    return out


def greedy_keep(clash: np.ndarray, ok: np.ndarray | None = None) -> np.ndarray:
    """Greedy suppression over ranked candidates: each candidate, best first, is kept when
    it is allowed and clashes with no candidate kept before it.

    Parameters
    ----------
    clash : (n, n) bool
        ``clash[i, j]``: candidate ``i`` (rank ``i``, 0 best) may not be kept beside the
        kept candidate ``j``.
    ok : (n,) bool, optional
        Candidates allowed at all (default: every one).

    Returns
    -------
    (k,) int64
        Ranks of the kept candidates, increasing.

    >>> clash = np.array([[1, 1, 0], [1, 1, 0], [0, 0, 1]], bool)
    >>> greedy_keep(clash).tolist(), greedy_keep(clash, np.array([False, True, True])).tolist()
    ([0, 2], [1, 2])
    """
    clash = np.asarray(clash, bool)
    alive = np.ones(len(clash), bool) if ok is None else np.array(ok, bool)
    keep: list[int] = []
    for i in range(len(clash)):
        if alive[i]:
            keep.append(i)
            alive &= ~clash[:, i]
    return np.array(keep, np.int64)


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Greedy non-maximum suppression by IoU.

    Parameters
    ----------
    boxes : (n, 4) float
        Boxes ``[x, y, w, h]``, pixels.
    scores : (n,) float
        Higher is better; ties keep the earlier box first.
    iou : float
        A box overlapping a kept one by more than this IoU is dropped.

    Returns
    -------
    (k,) int
        Indices of the kept boxes, best score first.

    >>> nms(np.array([[0, 0, 10, 10], [1, 0, 10, 10], [30, 0, 10, 10]]),
    ...     np.array([0.5, 0.9, 0.1]), 0.3).tolist()
    [1, 2]
    """
    b = _boxes(boxes)
    order = np.argsort(-np.asarray(scores, float), kind="stable")
    if not len(b):
        return np.zeros(0, int)
    ranked = b[order]
    return order[greedy_keep(iou_matrix(ranked, ranked) > iou)].astype(int)


def suppress(boxes: np.ndarray, order: np.ndarray, own: np.ndarray, others: np.ndarray,
             nms_iou: float, min_dist: float = 0.0) -> np.ndarray:
    """Greedy suppression of new instances of one RP against each other and the instances
    already found (RESCU-II's prediction).

    A candidate is dropped when, with a kept candidate or an instance of its own RP, its
    IoU exceeds ``nms_iou``, one box's centre lies in the other, the intersection covers
    more than half of the smaller box, or the centres are closer than ``min_dist``
    (instances of an RP recur at the lattice spacing); with an instance of another RP,
    when the IoU exceeds 0.5.

    Parameters
    ----------
    boxes : (P, 4) float
        Candidate boxes ``[x, y, w, h]``, pixels.
    order : (m,) int
        Indices into ``boxes`` of the candidates, best first.
    own : (N, 4) float
        Instances of the RP, ``[x, y, w, h]``, pixels.
    others : (M, 4) float
        Instances of the other RPs (may be empty), pixels.
    nms_iou : float
        IoU above which two instances of one RP clash, in (0, 1).
    min_dist : float
        Least distance between the centres of two instances of one RP, pixels.

    Returns
    -------
    (k,) int
        The kept entries of ``order``, in its order.

    >>> own = np.array([[0., 0, 10, 10]])
    >>> cand = np.array([[2., 0, 10, 10], [20, 0, 10, 10], [22, 0, 10, 10], [40, 0, 10, 10]])
    >>> suppress(cand, np.arange(4), own, np.zeros((0, 4)), 0.3).tolist()
    [1, 3]
    """
    if len(order) == 0:
        return order
    b = boxes[order]
    cb = b[:, :2] + b[:, 2:] / 2
    co = own[:, :2] + own[:, 2:] / 2
    near_own = np.linalg.norm(cb[:, None] - co[None], axis=2) < min_dist
    clash_own = ((iou_matrix(b, own) > nms_iou) | centre_in(b, own)
                 | (cover_matrix(b, own) > 0.5) | near_own).any(1)
    ok = ~clash_own
    if len(others):
        ok &= iou_matrix(b, others).max(1) <= 0.5
    pair = ((iou_matrix(b, b) > nms_iou) | centre_in(b, b) | (cover_matrix(b, b) > 0.5)
            | (np.linalg.norm(cb[:, None] - cb[None], axis=2) < min_dist))
    keep = greedy_keep(pair, ok)
    return order[keep] if len(keep) else order[:0]
