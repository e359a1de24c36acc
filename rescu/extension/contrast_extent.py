"""The extent of an RP's boxes (the dense source's whole objects,
:mod:`rescu.extension.objects`): one scale, aspect and shift for all of an RP's boxes,
where they stand out most from their surroundings.

* :func:`colour_contrast` — a Fisher ratio of each box's CIELAB colour against a ring
  around it (:func:`colour_integrals`, :func:`rect_sums`: summed-area tables);
* :func:`edge_contrast` — how much stronger the image's edges are on each box's outline
  than just outside it (:func:`gradient_integral`);
* :func:`extent_score` — the two combined, and :func:`refine_extent`, the search over
  the candidate transforms.

Boxes are ``[x, y, w, h]`` in pixels of the image given.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["colour_integrals", "rect_sums", "colour_contrast", "gradient_integral",
           "edge_contrast", "extent_score", "refine_extent"]


def colour_integrals(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Summed-area tables of an image's CIELAB values and of their squares.

    Parameters
    ----------
    rgb : (H, W, 3) uint8

    Returns
    -------
    (H + 1, W + 1, 3) float64 twice: sums of L, a, b and of their squares
    """
    import cv2

    lab = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2LAB).astype(np.float64)
    return cv2.integral(lab), cv2.integral(lab * lab)


def rect_sums(t: np.ndarray, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray,
              y1: np.ndarray) -> np.ndarray:
    """Sums over the rectangles ``[y0, y1) x [x0, x1)`` (int arrays, clipped by the
    caller) from a summed-area table ``t`` ((H + 1, W + 1[, c]), :func:`colour_integrals`)."""
    return t[y1, x1] - t[y0, x1] - t[y1, x0] + t[y0, x0]


def colour_contrast(integrals: tuple[np.ndarray, np.ndarray], boxes: np.ndarray,
                    ring: float = 0.5) -> np.ndarray:
    """How much the colour inside each box differs from a ring around it.

    ``|m_in - m_ring|^2 / (v_in + v_ring + 25)``: the squared distance of the mean CIELAB
    colours over the summed variances (a Fisher ratio; 25 = a noise floor of 5 grey
    levels), the ring being the box grown by ``ring`` x its width and height on each side
    (clipped to the image).

    Parameters
    ----------
    integrals : :func:`colour_integrals` of the image
    boxes : (n, 4) ``[x, y, w, h]``, pixels of that image
    ring : ring width / box side

    Returns
    -------
    (n,) float >= 0
    """
    ii, ii2 = integrals
    H, W = ii.shape[0] - 1, ii.shape[1] - 1
    b = np.asarray(boxes, float).reshape(-1, 4)
    x0 = np.clip(np.round(b[:, 0]), 0, W - 1).astype(int)
    y0 = np.clip(np.round(b[:, 1]), 0, H - 1).astype(int)
    x1 = np.clip(np.round(b[:, 0] + b[:, 2]), x0 + 1, W).astype(int)
    y1 = np.clip(np.round(b[:, 1] + b[:, 3]), y0 + 1, H).astype(int)
    rw = np.maximum(1, np.round(b[:, 2] * ring)).astype(int)
    rh = np.maximum(1, np.round(b[:, 3] * ring)).astype(int)
    X0, Y0 = np.clip(x0 - rw, 0, W), np.clip(y0 - rh, 0, H)
    X1, Y1 = np.clip(x1 + rw, 0, W), np.clip(y1 + rh, 0, H)

    si, si2 = rect_sums(ii, x0, y0, x1, y1), rect_sums(ii2, x0, y0, x1, y1)
    so, so2 = rect_sums(ii, X0, Y0, X1, Y1) - si, rect_sums(ii2, X0, Y0, X1, Y1) - si2
    ni = ((x1 - x0) * (y1 - y0)).astype(float)[:, None]
    no = np.maximum(((X1 - X0) * (Y1 - Y0)).astype(float)[:, None] - ni, 1.0)
    mi, mo = si / ni, so / no
    vi = np.maximum(si2 / ni - mi ** 2, 0).sum(1)
    vo = np.maximum(so2 / no - mo ** 2, 0).sum(1)
    return ((mi - mo) ** 2).sum(1) / (vi + vo + 25.0)


def gradient_integral(rgb: np.ndarray) -> np.ndarray:
    """Summed-area table of an image's gradient magnitude (3 x 3 Sobel on its grey
    levels), (H + 1, W + 1) float64."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float64)
    g = np.hypot(cv2.Sobel(grey, cv2.CV_64F, 1, 0, ksize=3),
                 cv2.Sobel(grey, cv2.CV_64F, 0, 1, ksize=3))
    return cv2.integral(g)


def edge_contrast(gradients: np.ndarray, boxes: np.ndarray, band: float = 0.1) -> np.ndarray:
    """How much stronger the image's edges are on each box's outline than around it.

    ``(g_band - g_out) / (g_out + 10)``: the mean gradient magnitude in the band
    straddling the box's border (``band`` x its width and height on each side of it)
    against that in the ring just outside the band (the next ``2 x band``), over the
    latter (10: a floor of a few grey levels per pixel). A box whose outline follows an
    object's silhouette (a car's outline, a window's frame) scores high; one inside the
    object or around it, where the border crosses texture or plain background, low.

    Parameters
    ----------
    gradients : :func:`gradient_integral` of the image
    boxes : (n, 4) ``[x, y, w, h]``, pixels of that image
    band : half the band's width / box side

    Returns
    -------
    (n,) float
    """
    H, W = gradients.shape[0] - 1, gradients.shape[1] - 1
    b = np.asarray(boxes, float).reshape(-1, 4)

    def sums(g: float) -> tuple[np.ndarray, np.ndarray]:
        # sum and area of the box grown by g x its sides on each side (g < 0: shrunk)
        x0 = np.clip(np.round(b[:, 0] - g * b[:, 2]), 0, W - 1).astype(int)
        y0 = np.clip(np.round(b[:, 1] - g * b[:, 3]), 0, H - 1).astype(int)
        x1 = np.clip(np.round(b[:, 0] + (1 + g) * b[:, 2]), x0 + 1, W).astype(int)
        y1 = np.clip(np.round(b[:, 1] + (1 + g) * b[:, 3]), y0 + 1, H).astype(int)
        return rect_sums(gradients, x0, y0, x1, y1), ((x1 - x0) * (y1 - y0)).astype(float)

    s_in, a_in = sums(-band)
    s_mid, a_mid = sums(band)
    s_out, a_out = sums(3 * band)
    g_band = (s_mid - s_in) / np.maximum(a_mid - a_in, 1.0)
    g_out = (s_out - s_mid) / np.maximum(a_out - a_mid, 1.0)
    return (g_band - g_out) / (g_out + 10.0)


def extent_score(integrals: tuple[np.ndarray, np.ndarray], boxes: np.ndarray, ring: float,
                 gradients: np.ndarray | None = None, edges: float = 0.0) -> np.ndarray:
    """What :func:`refine_extent` maximises: :func:`colour_contrast` against a ring
    ``ring`` x the box's sides wide, plus ``edges`` x :func:`edge_contrast` when
    ``edges`` > 0 (``gradients`` then required). (n,) float."""
    v = colour_contrast(integrals, boxes, ring)
    if edges > 0:
        if gradients is None:
            raise ValueError("extent_score: edges > 0 needs the gradient_integral")
        v = v + edges * edge_contrast(gradients, boxes)
    return v


def refine_extent(rgb: np.ndarray, boxes: np.ndarray, scales: Sequence[float],
                  aspects: Sequence[float], shifts: Sequence[float],
                  integrals: tuple[np.ndarray, np.ndarray] | None = None,
                  turn: bool = False, turned: np.ndarray | None = None, ring: float = 0.5,
                  edges: float = 0.0, gradients: np.ndarray | None = None
                  ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The RP's boxes at the extent where they stand out most from their surroundings.

    One transform for all boxes (they show the same kind of object): side ``scale`` x the
    median box side, width / height ``aspect``, centre moved by ``shift`` x the new width
    and height; the transform with the largest median :func:`colour_contrast` over the
    boxes that stay (mostly) inside the image wins (against a ring ``ring`` x the box's
    sides wide; with ``edges`` > 0 plus that weight x :func:`edge_contrast`,
    :func:`extent_score`). With ``turn`` and an elongated
    transform (aspect not 1), each box then takes the transform turned by 90 degrees
    (width and height swapped, and the two shifts) where that box's contrast is larger
    turned: the same kind of object lying the other way (cars parked across a row,
    seen from above). The boxes marked ``turned`` (found lying the other way,
    :func:`rescu.extension.turned.complete_turned`) always take the transform turned, in
    the choice too. Boxes are clipped to the image.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    boxes : (n, 4) ``[x, y, w, h]``, pixels of ``rgb``
    scales, aspects, shifts : the candidate transforms (1.0, 1.0, 0.0 included: the
        boxes as they are, squared to their median side)
    integrals : :func:`colour_integrals` of ``rgb`` when already computed
    turn : let each box take the transform turned by 90 degrees
    turned : (n,) bool or None, the boxes that take every transform turned
    ring : the contrast's ring width / box side (``dense.extent_ring``)
    edges : weight of :func:`edge_contrast` in the score (``dense.extent_edges``; 0: the
        colour contrast alone)
    gradients : :func:`gradient_integral` of ``rgb`` when already computed (made here
        when ``edges`` > 0 and None)

    Returns
    -------
    boxes : (n, 4) float, the refined boxes
    transform : ``(scale, aspect, shift_x, shift_y)`` chosen (for the boxes not turned)
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if not len(b):
        return b, (1.0, 1.0, 0.0, 0.0)
    ii = colour_integrals(rgb) if integrals is None else integrals
    if edges > 0 and gradients is None:
        gradients = gradient_integral(rgb)
    H, W = rgb.shape[:2]
    c = b[:, :2] + b[:, 2:] / 2
    side = float(np.median(np.sqrt(b[:, 2] * b[:, 3])))
    # every transform's boxes at once, (T, n, 4), in the order scale, aspect, dx, dy
    ts = [(float(s), float(r), float(dx), float(dy))
          for s in scales for r in aspects for dx in shifts for dy in shifts]
    t = np.array(ts, float).reshape(-1, 4)
    bw = side * t[:, 0] * np.sqrt(t[:, 1])
    bh = side * t[:, 0] / np.sqrt(t[:, 1])
    cx = c[None, :, 0] + (t[:, 2] * bw)[:, None]
    cy = c[None, :, 1] + (t[:, 3] * bh)[:, None]
    BW, BH = np.broadcast_to(bw[:, None], cx.shape), np.broadcast_to(bh[:, None], cx.shape)
    if turned is not None and np.any(turned):
        # turned boxes: width and height swapped, and the two shifts
        tm = np.asarray(turned, bool)[None, :]
        cx = np.where(tm, c[None, :, 0] + (t[:, 3] * bh)[:, None], cx)
        cy = np.where(tm, c[None, :, 1] + (t[:, 2] * bw)[:, None], cy)
        BW, BH = np.where(tm, BH, BW), np.where(tm, BW, BH)
    nb = np.stack([cx - BW / 2, cy - BH / 2, BW, BH], axis=2)
    inside = ((nb[..., 0] >= -0.15 * BW) & (nb[..., 1] >= -0.15 * BH)
              & (nb[..., 0] + BW <= W + 0.15 * BW) & (nb[..., 1] + BH <= H + 0.15 * BH))
    tried = np.flatnonzero(inside.mean(1) >= 0.7)
    best, best_t, best_v = b, (1.0, 1.0, 0.0, 0.0), -1.0
    if len(tried):
        v_all = extent_score(ii, nb[tried][inside[tried]], ring, gradients, edges)  # every box
        ends = np.cumsum(inside[tried].sum(1))
        for k, lo, hi in zip(tried, np.r_[0, ends[:-1]], ends):
            v = float(np.median(v_all[lo:hi]))
            if v > best_v + 1e-12:
                best, best_t, best_v = nb[k], ts[k], v
        if turn and abs(best_t[1] - 1.0) > 1e-9:
            # the same transform turned: width and height swapped, and the two shifts
            tw, th = best[:, 3], best[:, 2]
            tb = np.stack([c[:, 0] + best_t[3] * tw - tw / 2, c[:, 1] + best_t[2] * th - th / 2,
                           tw, th], axis=1)
            both = extent_score(ii, np.vstack([best, tb]), ring, gradients, edges)
            flip = both[len(b):] > both[:len(b)]
            best = np.where(flip[:, None], tb, best)
    x0 = np.clip(best[:, 0], 0, W)
    y0 = np.clip(best[:, 1], 0, H)
    x1 = np.clip(best[:, 0] + best[:, 2], 0, W)
    y1 = np.clip(best[:, 1] + best[:, 3], 0, H)
    return np.c_[x0, y0, x1 - x0, y1 - y0], best_t
