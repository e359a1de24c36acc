"""A tiny synthetic photo for the docstring examples of the public API (and for trying
RESCU without data): :func:`example_image`."""

from __future__ import annotations

import numpy as np


def example_image(n: int = 5, size: int = 48, gap: int = 32, seed: int = 0
                  ) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
    """A tiny synthetic photo for examples and doctests: one row of ``n`` copies of a
    random blocky texture (framed) on a smooth noise background.

    Returns the ``(H, W, 3)`` uint8 image (``H = 3 * size``, ``W = n * (size + gap) +
    gap``) and the copies' boxes ``(x, y, w, h)`` in pixels, left to right.

    >>> img, boxes = example_image(n=4)
    >>> img.shape, img.dtype, len(boxes), boxes[0]
    ((144, 352, 3), dtype('uint8'), 4, (32.0, 48.0, 48.0, 48.0))
    """
    import cv2

    rng = np.random.default_rng(seed)
    h, w = 3 * size, n * (size + gap) + gap
    bg = rng.integers(90, 140, (max(1, h // 4), max(1, w // 4))).astype(np.uint8)
    img = cv2.GaussianBlur(cv2.resize(bg, (w, h), interpolation=cv2.INTER_LINEAR), (0, 0), 2)
    tex = rng.integers(0, 256, (max(1, size // 6),) * 2).astype(np.uint8)
    tex = cv2.resize(tex, (size, size), interpolation=cv2.INTER_NEAREST)
    cv2.rectangle(tex, (2, 2), (size - 3, size - 3), 255, 2)
    boxes = []
    for i in range(n):
        x = gap + i * (size + gap)
        img[size:2 * size, x:x + size] = tex
        boxes.append((float(x), float(size), float(size), float(size)))
    return np.dstack([img] * 3), boxes
