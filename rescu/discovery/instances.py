"""The instances of one RP matrix in the image: boxes, feature points, extents, spread.

An RP matrix ``omega`` (M words x N instances, feature indices, -1 where a word is
missing in an instance; :class:`rescu.types.RPMatrix`) names which features of
:class:`rescu.types.Features` make each instance. These functions turn it into what the
image shows: each instance's box (the hull of its features, grown by their keypoint
radii), its feature points, duplicates (two parts of one object) and extents, and how
spread the word layout is (a straight edge is no object). Pixels of the processed image
unless said otherwise.
"""

from __future__ import annotations

import numpy as np

from ..boxes import cover_matrix
from ..layout import registered_centres
from ..types import Features


def layout_spread(xy: np.ndarray, omega: np.ndarray) -> float:
    """How two-dimensional the word layout of an instance is.

    Parameters
    ----------
    xy : (K, 2) float, pixels
    omega : (M, N) int, -1 for missing

    Returns
    -------
    float in [0, 1]
        sqrt(lambda_min / lambda_max) of the covariance of the within-instance offsets
        ``p_ij - c_j`` (``c_j`` the column centroid). Near 0 when every instance is a
        piece of one straight edge: an edge is self-similar along itself, so features
        on a long line form URPs of perfect affinity that are no recurring object.
    """
    pres = omega >= 0
    p = xy[np.where(pres, omega, 0)]
    cnt = pres.sum(0)
    c = (p * pres[..., None]).sum(0) / np.maximum(cnt, 1)[:, None]
    off = (p - c[None])[pres]
    if len(off) < 3:
        return 0.0
    # eigenvalues of the 2 x 2 covariance in closed form
    d = off - off.mean(axis=0)
    sxx, syy, sxy = (d[:, 0] @ d[:, 0], d[:, 1] @ d[:, 1], d[:, 0] @ d[:, 1])
    h = 0.5 * (sxx + syy)
    q = float(np.hypot(0.5 * (sxx - syy), sxy))
    lo, hi = h - q, h + q                               # lambda_min, lambda_max (x (n-1))
    return float(np.sqrt(max(lo, 0.0) / hi)) if hi > 0 else 0.0


def instance_boxes(features: Features, omega: np.ndarray, box_grow: float = 0.5) -> np.ndarray:
    """Instance boxes of an RP matrix, processed pixels.

    Parameters
    ----------
    omega : (M, N) int
        Feature indices, -1 for missing.
    box_grow : float
        The feature hull is grown by ``box_grow`` times the median keypoint radius.

    Returns
    -------
    (N, 4) float
        ``[x, y, w, h]`` clipped to the image.
    """
    w, h = features.image_size
    out = np.zeros((omega.shape[1], 4))
    for j in range(omega.shape[1]):
        idx = omega[:, j][omega[:, j] >= 0]
        p = features.xy[idx].astype(np.float64)
        g = box_grow * float(np.median(features.scale[idx])) / 2.0
        x0, y0 = max(0.0, p[:, 0].min() - g), max(0.0, p[:, 1].min() - g)
        x1, y1 = min(float(w), p[:, 0].max() + g), min(float(h), p[:, 1].max() + g)
        out[j] = [x0, y0, max(x1 - x0, 0.0), max(y1 - y0, 0.0)]
    return out


def feature_points(features: Features, omega: np.ndarray) -> np.ndarray:
    """Positions of an RP matrix's features, (M, N, 2) float, processed pixels; NaN where
    a word has no feature in an instance (``omega`` -1)."""
    om = np.asarray(omega, np.int64)
    xy = features.xy[np.where(om >= 0, om, 0)].astype(np.float64)
    return np.where((om >= 0)[..., None], xy, np.nan)


def drop_duplicate_instances(features: Features, omega: np.ndarray, box_grow: float = 0.5,
                             max_cover: float = 0.5, min_centre_distance: float = 0.5
                             ) -> np.ndarray:
    """Drop instances of an RP that duplicate another of its instances (one object twice).

    The search refuses a new instance whose feature box overlaps an existing one by IoU,
    which lets through a small box inside a large one, or two small boxes on two parts
    of one object (the count is one too high). Two instances are one object when

    * their boxes (:func:`instance_boxes`) overlap by more than ``max_cover`` of the
      smaller box's area, or
    * their registered centres (each word's typical offset from the instance centre
      removed, :func:`rescu.layout.registered_centres`) are closer than
      ``min_centre_distance`` times the RP's median larger box side.

    Instances are visited by decreasing number of words (ties: larger box, then lower
    index); one is kept when it duplicates no kept instance.

    Parameters
    ----------
    omega : (M, N) int
        Feature indices, -1 for missing.
    box_grow : float
        As :func:`instance_boxes`.
    max_cover : float
        Largest intersection over the smaller box's area, in (0, 1]; 1.0 turns the test off.
    min_centre_distance : float
        Fraction of the median larger box side, >= 0; 0 turns the test off.

    Returns
    -------
    (M, N') int64
        The kept columns in their original order (N' <= N).
    """
    om = np.asarray(omega, np.int64)
    if om.ndim != 2 or om.shape[1] < 2:
        return om
    b = instance_boxes(features, om, box_grow)
    dup = cover_matrix(b, b) > max_cover if max_cover < 1.0 else np.zeros((len(b),) * 2, bool)
    if min_centre_distance > 0:
        reg = registered_centres(b[:, :2] + b[:, 2:] / 2, feature_points(features, om))
        d = np.linalg.norm(reg[:, None] - reg[None], axis=2)
        dup |= d < min_centre_distance * float(np.median(b[:, 2:].max(axis=1)))
    words = (om >= 0).sum(axis=0)
    order = sorted(range(om.shape[1]), key=lambda j: (-words[j], -b[j, 2] * b[j, 3], j))
    kept: list[int] = []
    for j in order:
        if not kept or not dup[j, kept].any():
            kept.append(j)
    return om[:, sorted(kept)]


def instance_extents(features: Features, omega: np.ndarray, box_grow: float = 0.5,
                     extent_grow: float = 0.5) -> np.ndarray:
    """The image region each instance of an RP occupies, processed pixels.

    The feature hull (:func:`instance_boxes`) covers only the part of an object that has
    recurring keypoints; the object itself extends further. An instance's extent is its
    box grown on every side to half the distance to the nearest other instance centre
    (an instance is at most one period wide), by at most ``extent_grow`` times the
    box's larger side. Features inside an extent belong to that object and may not
    start another RP (otherwise other parts of the same objects reappear as a second,
    spurious RP).

    Returns
    -------
    (N, 4) float
        ``[x, y, w, h]`` clipped to the image.
    """
    b = instance_boxes(features, omega, box_grow)
    n = len(b)
    if n == 0:
        return b
    w, h = features.image_size
    c = b[:, :2] + b[:, 2:] / 2.0
    d = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 1] - c[None, :, 1])
    np.fill_diagonal(d, np.inf)
    half_nn = 0.5 * d.min(axis=1) if n > 1 else np.zeros(1)
    half = b[:, 2:] / 2.0
    cap = half + extent_grow * b[:, 2:].max(axis=1, keepdims=True)
    half = np.clip(half_nn[:, None], half, cap)
    x0 = np.clip(c[:, 0] - half[:, 0], 0, w)
    y0 = np.clip(c[:, 1] - half[:, 1], 0, h)
    x1 = np.clip(c[:, 0] + half[:, 0], 0, w)
    y1 = np.clip(c[:, 1] + half[:, 1], 0, h)
    return np.stack([x0, y0, x1 - x0, y1 - y0], axis=1)
