"""Box phase and extent of an RP's instances from the edges they share.

Stage I's instance box is the hull of the RP's recurring keypoints, grown a little. On
real photos that hull often sits at the wrong phase and size: on a facade the keypoints
of a window and of the balcony below it recur together, and the box straddles the two
objects (half a window, half a railing), so it matches neither. The object itself is
bounded by edges that every instance shares: a window's frame, a car's outline.

:func:`refine_pattern_boxes` looks for them in the instances' *mean gradient frame*:
every instance's neighbourhood (twice its box, centred on it) is resampled to one
``2S x 2S`` frame, where the box is the central ``S x S`` square, and the absolute
horizontal and vertical image gradients are averaged over the instances
(:func:`mean_gradient_frame`). Edges that recur at one place relative to the instances
add up; others average out. One shift and one scale per RP (:func:`edge_box_transform`),
applied to all its instances, moves the box so that its four sides lie on the strongest
shared edges: the score of a candidate box is the mean strength of vertical edges along
its left and right sides plus that of horizontal edges along its top and bottom (each
relative to the frame's mean, a side found within one frame pixel).

Measured on every image of the real sets in ``../shared/data`` (docs/results.md): the
instance precision of RESCU-I rises on every set, most on facades.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from ..types import Pattern

FRAME = 32
"""S: the box side in the mean gradient frame, frame pixels (the frame is 2S x 2S)."""


def gradient_images(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Absolute Sobel derivatives of a grey image: (|d/dx|, |d/dy|), each (H, W) float32."""
    g = np.asarray(gray, np.float32)
    if g.ndim != 2:
        raise ValueError(f"gray must be (H, W), got shape {g.shape}")
    return (np.abs(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)),
            np.abs(cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)))


def mean_gradient_frame(gx: np.ndarray, gy: np.ndarray, boxes: np.ndarray,
                        size: int = FRAME) -> tuple[np.ndarray, np.ndarray]:
    """The instances' mean gradient frame.

    Parameters
    ----------
    gx, gy : (H, W) float32
        Absolute image derivatives (:func:`gradient_images`).
    boxes : (N, 4) float
        ``[x, y, w, h]`` of the instances, pixels of ``gx``; w, h > 0.
    size : int
        S; each box's neighbourhood ``[cx - w, cx + w] x [cy - h, cy + h]`` is resampled
        (bilinear, zero outside the image) to ``2S x 2S``.

    Returns
    -------
    (2S, 2S) float64, (2S, 2S) float64
        Mean |d/dx| and mean |d/dy| over the instances.
    """
    n = 2 * size
    ax = np.zeros((n, n))
    ay = np.zeros((n, n))
    for x, y, w, h in np.asarray(boxes, float):
        cx, cy = x + w / 2.0, y + h / 2.0
        m = np.array([[size / w, 0.0, -(cx - w) * size / w],
                      [0.0, size / h, -(cy - h) * size / h]])
        ax += cv2.warpAffine(gx, m, (n, n), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT)
        ay += cv2.warpAffine(gy, m, (n, n), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT)
    k = max(len(boxes), 1)
    return ax / k, ay / k


def edge_box_transform(ax: np.ndarray, ay: np.ndarray, shifts: Sequence[float],
                       scales: Sequence[float]) -> tuple[float, float, float, float]:
    """The shift and scale of the box whose sides lie on the strongest frame edges.

    Parameters
    ----------
    ax, ay : (2S, 2S) float
        Mean gradient frame (:func:`mean_gradient_frame`); the box is the central S x S.
    shifts : sequence of float
        Candidate shifts of the box centre, fractions of the box side (x and y alike).
    scales : sequence of float
        Candidate scales of the box side (x and y alike, independently).

    Returns
    -------
    (dx, dy, sx, sy)
        Centre shift (fractions of the box width / height) and side scales; the first
        best candidate in the order dx, dy, sx, sy of the inputs; (0, 0, 1, 1) when no
        candidate fits in the frame.
    """
    n = ax.shape[0]
    s = n // 2
    ex = np.maximum.reduce([np.roll(ax, k, axis=1) for k in (-1, 0, 1)]) / (ax.mean() + 1e-9)
    ey = np.maximum.reduce([np.roll(ay, k, axis=0) for k in (-1, 0, 1)]) / (ay.mean() + 1e-9)
    cx = np.vstack([np.zeros((1, n)), np.cumsum(ex, axis=0)])   # column sums over rows
    cy = np.hstack([np.zeros((n, 1)), np.cumsum(ey, axis=1)])   # row sums over columns
    dx, dy, sx, sy = (a.ravel() for a in np.meshgrid(np.asarray(shifts, float),
                                                     np.asarray(shifts, float),
                                                     np.asarray(scales, float),
                                                     np.asarray(scales, float),
                                                     indexing="ij"))
    x0 = np.rint(s + (dx - sx / 2) * s).astype(int)
    x1 = np.rint(s + (dx + sx / 2) * s).astype(int)
    y0 = np.rint(s + (dy - sy / 2) * s).astype(int)
    y1 = np.rint(s + (dy + sy / 2) * s).astype(int)
    ok = (x0 >= 1) & (y0 >= 1) & (x1 <= n - 2) & (y1 <= n - 2) & (x1 - x0 >= 4) & (y1 - y0 >= 4)
    if not ok.any():
        return 0.0, 0.0, 1.0, 1.0
    x0, x1, y0, y1 = x0[ok], x1[ok], y0[ok], y1[ok]
    hgt, wid = (y1 - y0).astype(float), (x1 - x0).astype(float)
    score = ((cx[y1, x0] - cx[y0, x0]) / hgt + (cx[y1, x1] - cx[y0, x1]) / hgt
             + (cy[y0, x1] - cy[y0, x0]) / wid + (cy[y1, x1] - cy[y1, x0]) / wid)
    i = int(np.flatnonzero(ok)[int(np.argmax(score))])
    return float(dx[i]), float(dy[i]), float(sx[i]), float(sy[i])


def transform_boxes(boxes: np.ndarray, t: tuple[float, float, float, float],
                    image_size: tuple[int, int]) -> np.ndarray:
    """Boxes moved by ``t = (dx, dy, sx, sy)`` (:func:`edge_box_transform`) and clipped
    to ``image_size`` = (W, H); (N, 4) float ``[x, y, w, h]``."""
    b = np.asarray(boxes, float)
    dx, dy, sx, sy = t
    w, h = b[:, 2] * sx, b[:, 3] * sy
    cx = b[:, 0] + b[:, 2] * (0.5 + dx)
    cy = b[:, 1] + b[:, 3] * (0.5 + dy)
    x0 = np.clip(cx - w / 2, 0, image_size[0])
    y0 = np.clip(cy - h / 2, 0, image_size[1])
    x1 = np.clip(cx + w / 2, 0, image_size[0])
    y1 = np.clip(cy + h / 2, 0, image_size[1])
    return np.stack([x0, y0, x1 - x0, y1 - y0], axis=1)


def refine_pattern_boxes(gray: np.ndarray, scale_factor: float, patterns: list[Pattern],
                         shifts: Sequence[float], scales: Sequence[float]) -> list[Pattern]:
    """Every pattern's instance boxes moved onto the edges its instances share.

    Parameters
    ----------
    gray : (H, W) array
        The processed image, grey.
    scale_factor : float
        processed = original x scale_factor; the patterns' boxes are in original pixels.
    patterns : list of Pattern
        Modified in place: each instance's ``bbox`` (one transform per pattern; a
        pattern with a box of zero width or height is left as it is), and
        ``extra["box_transform"]`` = ``[dx, dy, sx, sy]`` (:func:`edge_box_transform`;
        :func:`untransform_boxes` gives the boxes before it, for stage II's merge).
    shifts, scales : sequence of float
        As :func:`edge_box_transform`.

    Returns
    -------
    list of Pattern
        ``patterns``.
    """
    if not patterns:
        return patterns
    gx, gy = gradient_images(gray)
    size = (gray.shape[1] / scale_factor, gray.shape[0] / scale_factor)
    for p in patterns:
        b = np.array([i.bbox for i in p.instances], float)
        if len(b) == 0 or (b[:, 2:] <= 0).any():
            continue
        ax, ay = mean_gradient_frame(gx, gy, b * scale_factor)
        t = edge_box_transform(ax, ay, shifts, scales)
        nb = transform_boxes(b, t, size)
        for inst, box in zip(p.instances, nb):
            inst.bbox = (float(box[0]), float(box[1]), float(box[2]), float(box[3]))
        p.extra["box_transform"] = [float(v) for v in t]
    return patterns


def untransform_boxes(boxes: np.ndarray, t: Sequence[float] | None) -> np.ndarray:
    """The boxes before :func:`transform_boxes` with ``t = (dx, dy, sx, sy)``.

    Exact for a box that was not clipped at the image border (a clipped one comes back
    with the clipped side's share of the shift and scale); ``t`` None: ``boxes``.

    Parameters
    ----------
    boxes : (N, 4) float ``[x, y, w, h]``, moved boxes
    t : the transform a pattern's ``extra["box_transform"]`` records, or None

    Returns
    -------
    (N, 4) float, the same pixels

    Raises ValueError when ``t`` is not four numbers with positive scales.

    >>> b = np.array([[10.0, 20.0, 30.0, 40.0]])
    >>> t = (0.1, -0.2, 1.2, 0.8)
    >>> untransform_boxes(transform_boxes(b, t, (1000, 1000)), t).round(6).tolist()
    [[10.0, 20.0, 30.0, 40.0]]
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if t is None:
        return b.copy()
    if len(t) != 4 or not float(t[2]) > 0 or not float(t[3]) > 0:
        raise ValueError(f"box_transform must be [dx, dy, sx, sy] with sx, sy > 0, got {t}")
    dx, dy, sx, sy = (float(v) for v in t)
    w, h = b[:, 2] / sx, b[:, 3] / sy
    cx = b[:, 0] + b[:, 2] / 2 - w * dx
    cy = b[:, 1] + b[:, 3] / 2 - h * dy
    return np.stack([cx - w / 2, cy - h / 2, w, h], axis=1)


def unrefined_boxes(p: Pattern) -> np.ndarray:
    """All instance boxes of ``p`` (K, 4) before RESCU-I's box refinement: its
    ``extra["box_transform"]`` undone (:func:`untransform_boxes`), the boxes as they are
    when it has none. What stage II's split-RP merge compares."""
    b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    return untransform_boxes(b, p.extra.get("box_transform"))
