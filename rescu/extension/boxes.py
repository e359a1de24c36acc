"""Box geometry of RESCU-II: IoU and cover matrices, the size gate, centre containment and
the greedy suppression of new instances against each other and the stage-I instances."""

from __future__ import annotations

import numpy as np


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from ..evaluation.metrics import iou_matrix

    return iou_matrix(a, b)


def box_cover(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """intersection / min(area a, area b), (A, B)."""
    from ..evaluation.metrics import cover_matrix

    return cover_matrix(a, b)


def size_gate(boxes: np.ndarray, inst: np.ndarray, tol: float) -> np.ndarray:
    """(P,) bool: width and height of the box within a factor ``tol`` of those of some
    instance (the size gate; per instance, so RPs of mixed sizes keep all their sizes)."""
    b = np.asarray(boxes, float).reshape(-1, 1, 4)
    i = np.asarray(inst, float).reshape(1, -1, 4)
    rw = b[..., 2] / np.maximum(i[..., 2], 1e-9)
    rh = b[..., 3] / np.maximum(i[..., 3], 1e-9)
    return ((rw <= tol) & (rw >= 1 / tol) & (rh <= tol) & (rh >= 1 / tol)).any(1)


def centre_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) bool: the centre of a_i lies inside b_j or the centre of b_j inside a_i."""
    a = np.asarray(a, float).reshape(-1, 4)
    b = np.asarray(b, float).reshape(-1, 4)

    def inside(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        c = p[:, :2] + p[:, 2:] / 2
        return ((c[:, None, 0] >= q[None, :, 0]) & (c[:, None, 0] <= q[None, :, 0] + q[None, :, 2])
                & (c[:, None, 1] >= q[None, :, 1]) & (c[:, None, 1] <= q[None, :, 1] + q[None, :, 3]))

    return inside(a, b) | inside(b, a).T


def suppress(boxes: np.ndarray, order: np.ndarray, own: np.ndarray, others: np.ndarray,
              nms_iou: float, min_dist: float = 0.0) -> np.ndarray:
    """Greedy NMS of candidate ``order`` (best first) against each other and stage I.

    A candidate is dropped when, with a kept candidate or a stage-I instance of its own
    RP, its IoU exceeds ``nms_iou``, one box's centre lies in the other, or the
    intersection covers more than half of the smaller box, or the box centres are closer
    than ``min_dist`` (pixels; instances of an RP recur at the lattice spacing); with a
    stage-I instance of another RP, when the IoU exceeds 0.5.
    """
    if len(order) == 0:
        return order
    b = boxes[order]
    cb = b[:, :2] + b[:, 2:] / 2
    co = own[:, :2] + own[:, 2:] / 2
    near_own = np.linalg.norm(cb[:, None] - co[None], axis=2) < min_dist
    clash_own = ((box_iou(b, own) > nms_iou) | centre_in(b, own) | (box_cover(b, own) > 0.5)
                 | near_own).any(1)
    ok = ~clash_own
    if len(others):
        ok &= box_iou(b, others).max(1) <= 0.5
    pair = ((box_iou(b, b) > nms_iou) | centre_in(b, b) | (box_cover(b, b) > 0.5)
            | (np.linalg.norm(cb[:, None] - cb[None], axis=2) < min_dist))
    keep: list[int] = []
    for i in range(len(order)):
        if ok[i] and not any(pair[i, j] for j in keep):
            keep.append(i)
    return order[np.array(keep, np.int64)] if keep else order[:0]
