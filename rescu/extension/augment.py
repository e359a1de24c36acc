"""RESCU-II's augmentation: global transforms of the image copies, random occluders over
instances (local appearance deformation), geometric jitter of the instance boxes and the
hard negatives derived from them."""

from __future__ import annotations

import numpy as np

from ..boxes import iou_matrix
from .params import Stage2Params


def augment_image(rgb: np.ndarray, k: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray, bool]:
    """k-th global augmentation: returns (image, [sx, sy] box scale, hflip)."""
    import cv2

    h, w = rgb.shape[:2]
    img = rgb.astype(np.float32)
    kind = k % 3
    flip = kind == 0
    s = 1.0
    if kind == 0:                       # horizontal flip + mild contrast change
        img = img[:, ::-1] * rng.uniform(0.85, 1.15) + rng.uniform(-15, 15)
    elif kind == 1:                     # blur + brightness (stage I misses blurred ones)
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(1.0, 2.0)) + rng.uniform(-20, 20)
    else:                               # rescale + colour gain
        s = float(rng.uniform(0.75, 0.9))
        img = cv2.resize(img, (max(16, round(w * s)), max(16, round(h * s))),
                         interpolation=cv2.INTER_AREA)
        img = img * rng.uniform(0.85, 1.15, size=3)[None, None, :]
    out = np.clip(img, 0, 255).astype(np.uint8)
    oh, ow = out.shape[:2]
    return np.ascontiguousarray(out), np.array([ow / w, oh / h], np.float32), flip


def occlude_instances(rgb: np.ndarray, boxes: np.ndarray, prob: float,
                      fraction: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Cover part of some instance boxes with random occluders (random erasing).

    Each box is picked with probability ``prob``; its occluder is a band from a random
    side (left, right, top or bottom) covering a uniform share in ``fraction`` of the
    box, filled with a random colour plus Gaussian noise (sigma 12 grey levels).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    boxes : (N, 4) float
        ``[x, y, w, h]`` in the pixels of ``rgb``.
    prob : float
        In [0, 1].
    fraction : (float, float)
        0 <= min <= max <= 1.
    rng : numpy Generator

    Returns
    -------
    (H, W, 3) uint8
        A copy of ``rgb`` (``rgb`` itself is not changed).
    """
    out = np.array(rgb, np.uint8, copy=True)
    H, W = out.shape[:2]
    for x, y, w, h in np.asarray(boxes, np.float64).reshape(-1, 4):
        if rng.random() >= prob:
            continue
        side = int(rng.integers(4))
        f = float(rng.uniform(fraction[0], fraction[1]))
        x0, y0, x1, y1 = x, y, x + w, y + h
        if side == 0:
            x1 = x + f * w
        elif side == 1:
            x0 = x1 - f * w
        elif side == 2:
            y1 = y + f * h
        else:
            y0 = y1 - f * h
        c0, r0 = max(0, int(round(x0))), max(0, int(round(y0)))
        c1, r1 = min(W, int(round(x1))), min(H, int(round(y1)))
        if c1 <= c0 or r1 <= r0:
            continue
        fill = rng.uniform(0, 255, 3)[None, None, :] + rng.normal(0, 12, (r1 - r0, c1 - c0, 1))
        out[r0:r1, c0:c1] = np.clip(fill, 0, 255).astype(np.uint8)
    return out


def transform_boxes(b: np.ndarray, scale: np.ndarray, flip: bool, width: int) -> np.ndarray:
    b = np.asarray(b, np.float32).reshape(-1, 4).copy()
    if flip:
        b[:, 0] = width - b[:, 0] - b[:, 2]
    b[:, [0, 2]] *= scale[0]
    b[:, [1, 3]] *= scale[1]
    return b


def jitter_boxes(inst: np.ndarray, rp_of: np.ndarray, n: int, params: Stage2Params,
                  rng: np.random.Generator, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Geometric deformation of the instance boxes (processed px), n per instance."""
    if n <= 0 or len(inst) == 0:
        return np.zeros((0, 4), np.float32), np.zeros((0,), np.int64)
    boxes, parent = [], []
    for r in np.unique(rp_of):
        idx = np.nonzero(rp_of == r)[0]
        wh = inst[idx, 2:]
        # spread of the instance sizes of this RP (relative): drives the deformation
        rel = float(np.mean(np.std(wh, 0) / np.maximum(np.mean(wh, 0), 1e-6)))
        a = max(params.examples.min_jitter, params.examples.jitter * rel)
        for i in idx:
            x, y, w, h = inst[i]
            for _ in range(n):
                dx, dy = rng.uniform(-a, a, 2) * (w, h)
                sw, sh = np.exp(rng.uniform(-a, a, 2))
                nw, nh = w * sw, h * sh
                boxes.append([x + w / 2 + dx - nw / 2, y + h / 2 + dy - nh / 2, nw, nh])
                parent.append(i)
    from .proposals import clip_boxes

    return clip_boxes(np.array(boxes, np.float32), size), np.array(parent, np.int64)


def hard_negatives(inst: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Instance boxes shifted by half their size (8 directions) and doubled (processed px)."""
    W, H = size
    out = []
    for x, y, w, h in inst:
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)):
            out.append([x + dx * w / 2, y + dy * h / 2, w, h])
        out.append([x - w / 2, y - h / 2, 2 * w, 2 * h])
    b = np.array(out, np.float32).reshape(-1, 4)
    inside = (b[:, 0] >= 0) & (b[:, 1] >= 0) & (b[:, 0] + b[:, 2] <= W) & (b[:, 1] + b[:, 3] <= H)
    b = b[inside]
    if len(b) and len(inst):
        b = b[iou_matrix(b, inst).max(1) < 0.4]
    return b
