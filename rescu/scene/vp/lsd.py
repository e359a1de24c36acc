"""The line baseline: LSD segments + the same RANSAC (:func:`line_vanishing_point`).

LSD line segments (``cv2.createLineSegmentDetector``) longer than ``lsd_min_length`` x
the image diagonal, weighted by their lengths (a stand-in for Zhou, Farhat and Wang
2017); the dominant VP (largest inlier length) is returned.
"""

from __future__ import annotations

import numpy as np

from ...types import VanishingPoint
from .geometry import _canonical, inside_image
from .lines import Lines
from .params import VPParams
from .ransac import ransac_vp


def lsd_segments(gray: np.ndarray, min_length: float = 0.0,
                 max_segments: int | None = None) -> np.ndarray:
    """LSD line segments of a grayscale (H, W) or RGB (H, W, 3) uint8 image.

    Returns (L, 4) float ``[x1, y1, x2, y2]`` pixels, at least ``min_length`` pixels long,
    the longest ``max_segments`` (ordered by decreasing length).
    """
    import cv2

    img = np.asarray(gray)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ValueError(f"gray must have shape (H, W) or (H, W, 3), got {img.shape}")
    img = np.ascontiguousarray(img, dtype=np.uint8)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    segs = lsd.detect(img)[0]
    if segs is None:
        return np.zeros((0, 4))
    s = segs.reshape(-1, 4).astype(float)
    length = np.linalg.norm(s[:, 2:] - s[:, :2], axis=1)
    order = np.lexsort((np.arange(len(s)), -length))
    s, length = s[order], length[order]
    s = s[length >= min_length]
    if max_segments is not None:
        s = s[:max_segments]
    return s


def line_vanishing_point(rgb: np.ndarray, params: VPParams = VPParams(),
                         scale_factor: float = 1.0) -> VanishingPoint | None:
    """Baseline dominant VP from explicit LSD line segments + RANSAC.

    Parameters
    ----------
    rgb : (H, W, 3) or (H, W) uint8
        The processed image (original * ``scale_factor``).
    params : VPParams
    scale_factor : float
        processed = original * scale_factor; the VP is returned in original pixels.

    Returns
    -------
    VanishingPoint or None
        Segments weighted by length; ``support`` = number of inlier segments.
    """
    if scale_factor <= 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    h, w = np.asarray(rgb).shape[:2]
    diag = float(np.hypot(w, h))
    segs = lsd_segments(rgb, params.lsd_min_length * diag, params.lsd_max_segments)
    vp = ransac_vp(Lines.from_segments(segs), (w, h), params)
    if vp is None:
        return None
    v = _canonical(np.diag([1.0, 1.0, scale_factor]) @ vp.homogeneous)
    orig = (round(w / scale_factor), round(h / scale_factor))
    return VanishingPoint(v, inside_image(v, orig), vp.support)
