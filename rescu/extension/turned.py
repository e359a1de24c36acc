"""Feature maps of the dense source, and objects lying the other way.

:func:`hypercolumn` is the backbone's stride-8 + stride-16 map of an image (optionally
the mean over turned copies); :func:`level_image` the image a map of
:func:`rescu.extension.dense.dense_levels` sees; :func:`turned_map` the map of the image
turned by 90 degrees, turned back onto the plain map's cells; :func:`complete_turned` the
completion of a group (:func:`rescu.extension.objects.complete_group`) on both maps, for
objects of its kind lying the other way (cars parked across a row, seen from above).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..boxes import nms
from .boxmaps import group_prototype
from .objects import complete_group, similarity_map, window_peaks

__all__ = ["hypercolumn", "level_image", "turned_map", "complete_turned"]


def hypercolumn(backbone: Any, rgb: np.ndarray, rotations: int = 1) -> np.ndarray:
    """The stride-8 and stride-16 maps of ``backbone`` on ``rgb``, concatenated.

    With ``rotations`` 2 or 4 each half is the mean of the (unit) maps of the image turned
    by 0 and 90 degrees, or by every right angle, each turned back: a car seen from
    above lengthwise and one seen crosswise then get the same feature (the backbone
    itself is not rotation invariant, and the dense source's grouping split the cars
    of one photo by their orientation). The image is first padded (reflected) to a
    multiple of 16 pixels, so that the turned maps' cells fall on the same pixels, and
    the mean is cut to the plain map's cells.

    Parameters
    ----------
    backbone : rescu.extension.backbone.FrozenBackbone
    rgb : (H, W, 3) uint8
    rotations : int
        1 (one pass, the plain map), 2 or 4 backbone passes.

    Returns
    -------
    (C, H // 8, W // 8) float32 (EfficientNet-Lite0's maps round down): each half
    L2-normalised per location and scaled by 1 / sqrt(2), so every location has unit
    norm.
    """
    import torch
    import torch.nn.functional as F

    if rotations not in (1, 2, 4):
        raise ValueError(f"rotations must be 1, 2 or 4, got {rotations}")
    if rotations == 1:
        f8, f16 = backbone.multiscale_maps(rgb)
        with torch.no_grad():
            f8 = F.normalize(f8, dim=1)
            f16 = F.normalize(f16, dim=1)
    else:
        h, w = rgb.shape[:2]
        im = np.pad(rgb, ((0, -h % 16), (0, -w % 16), (0, 0)), mode="reflect")
        s8 = s16 = None
        for k in range(rotations):
            a8, a16 = backbone.multiscale_maps(np.ascontiguousarray(np.rot90(im, k)))
            with torch.no_grad():
                a8 = torch.rot90(F.normalize(a8, dim=1), -k, (2, 3))
                a16 = torch.rot90(F.normalize(a16, dim=1), -k, (2, 3))
            s8 = a8 if s8 is None else s8 + a8
            s16 = a16 if s16 is None else s16 + a16
        with torch.no_grad():     # the plain map's cells: h // 8 x w // 8
            f8 = F.normalize(s8[:, :, :h // 8, :w // 8], dim=1)
            f16 = F.normalize(s16[:, :, :(h // 8 + 1) // 2, :(w // 8 + 1) // 2], dim=1)
    with torch.no_grad():
        f16 = F.interpolate(f16, size=f8.shape[2:], mode="bilinear", align_corners=False)
        f = torch.cat([f8, f16], 1)[0] / np.sqrt(2.0)
    return np.ascontiguousarray(f.numpy(), dtype=np.float32)


def turned_map(backbone: Any, rgb: np.ndarray, rotations: int = 1,
               cells: tuple[int, int] | None = None) -> np.ndarray:
    """:func:`hypercolumn` of ``rgb`` turned by 90 degrees, turned back onto the cells of
    ``rgb``'s own map: at each cell, the features of what lies there as it looks turned
    (a car parked across the row looks like one parked along it). One backbone pass
    (``rotations`` passes with ``rotations`` > 1). The image is first padded (reflected)
    to a multiple of 16 pixels, as :func:`hypercolumn` does for its turned maps, so that
    the cells fall on the same pixels.

    Parameters
    ----------
    backbone : rescu.extension.backbone.FrozenBackbone
    rgb : (H, W, 3) uint8, the image of the map (a level's, :func:`level_image`)
    rotations : int, as :func:`hypercolumn`
    cells : ``(h, w)`` of the plain map (None: ``(H // 8, W // 8)``)

    Returns
    -------
    (C, h, w) float32, unit norm per cell
    """
    h, w = rgb.shape[:2]
    im = np.pad(np.asarray(rgb), ((0, -h % 16), (0, -w % 16), (0, 0)), mode="reflect")
    f = np.rot90(hypercolumn(backbone, np.ascontiguousarray(np.rot90(im, 1)), rotations),
                 -1, axes=(1, 2))
    ch, cw = cells if cells is not None else (h // 8, w // 8)
    f = f[:, :ch, :cw]        # the padding's cells (the plain map has none of them)
    if f.shape[1:] != (ch, cw):   # not with EfficientNet-Lite0's maps
        f = np.pad(f, ((0, 0), (0, ch - f.shape[1]), (0, cw - f.shape[2])), mode="edge")
    return np.ascontiguousarray(f, dtype=np.float32)


def level_image(rgb: np.ndarray, s: float) -> np.ndarray:
    """``rgb`` resized by ``s``, as the maps of
    :func:`rescu.extension.dense.dense_levels` see it (area
    interpolation when shrinking, linear when enlarging; ``rgb`` itself at 1)."""
    import cv2

    if s == 1:
        return rgb
    return cv2.resize(np.asarray(rgb), None, fx=s, fy=s,
                      interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)


def complete_turned(f: np.ndarray, turned: np.ndarray, cell_px: float, boxes: np.ndarray,
                    margin: float, floor: float, quantile: float = 20.0,
                    integral: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`rescu.extension.objects.complete_group` on ``f``, and the same prototype
    correlated over
    ``turned``, the map of the image turned by 90 degrees and turned back
    (:func:`turned_map`), with the window turned too: objects of the
    RP's kind lying the other way (a car parked across the row of the group's cars, seen
    from above) look there like the group's objects do on ``f``. Their peaks above the
    same threshold get the box turned (width and height swapped); the peaks of both maps
    are suppressed together at IoU 0.2, the more similar kept.

    The backbone is not rotation invariant: a car and a car turned by 90 degrees are less
    alike on one map than two cars lying the same way, and turning every map into a mean
    over orientations (``dense.rotations``) makes asphalt and roofs more like the cars too.
    Here each map keeps its own orientation; only the prototype is looked for in both.

    Parameters
    ----------
    f : (C, h, w) float32, unit norm per cell (:func:`hypercolumn`)
    turned : (C, h, w) float32, the turned map on the same cells
    cell_px, boxes, margin, floor, quantile, integral : as
        :func:`rescu.extension.objects.complete_group`

    Returns
    -------
    boxes : (n, 4) ``[x, y, w, h]``, pixels of the map's input, best similarity first
    sims : (n,) their similarity to the prototype (on the map each was found on)
    is_turned : (n,) bool, found on ``turned`` (box turned)
    """
    if turned.shape != f.shape:
        raise ValueError(f"turned map {turned.shape} and map {f.shape} differ in shape")
    b = np.asarray(boxes, float).reshape(-1, 4)
    pro = group_prototype(f, cell_px, b, integral) if len(b) else None
    ob, osims, tau, _ = complete_group(f, cell_px, b, margin, floor, quantile, integral, pro)
    if pro is None:
        return ob, osims, np.zeros(len(ob), bool)
    proto, _, (bw, bh), (sw, sh) = pro
    sim = similarity_map(turned, proto, (sh, sw))          # the window turned
    tb, ts = window_peaks(sim, (sh, sw), tau, cell_px, (bh, bw))
    allb = np.vstack([ob.reshape(-1, 4), tb])
    alls = np.r_[osims, ts]
    is_t = np.r_[np.zeros(len(ob), bool), np.ones(len(tb), bool)]
    keep = nms(allb, alls, 0.2)
    order = keep[np.argsort(-alls[keep], kind="stable")]
    return allb[order].reshape(-1, 4), alls[order], is_t[order]
