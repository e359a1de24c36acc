"""Checkerboards: a two-colour tiling found in the image, so that stage I's RPs sampling
it can be set aside.

Stage I's keypoints recur on any texture that repeats, and a board's squares repeat more
than anything else in a photo of a game. RPs that tile the plane are not reported (the
dense source's abutting test, ``dense.max_touching``), but stage I's boxes on a board lie
inside its squares, on their wood, and do not abut. The tiling itself is found here:
OpenCV's sector-based checkerboard detector (``cv2.findChessboardCornersSBWithMeta``,
weight-free, perspective-tolerant) finds the X-corners where two light and two dark
squares meet; the board is the grid of those corners extended by a few squares on every
side (the squares around the outer corners, which pieces or the frame may hide, and the
board's frame). Facades rarely have such corners: a window meets the wall in L- and
T-junctions, not in X-corners between alternating cells.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np


class BoardParams(Protocol):
    """The ``checkerboard_*`` fields :func:`board_outline` reads (those of
    :class:`rescu.discovery.sources.DenseParams`, which imports this module)."""

    checkerboard_min_corners: int
    checkerboard_border: int
    checkerboard_min_alternation: float
    checkerboard_seed: int

PROBE = (3, 3)
"""Smallest corner grid the detector looks for (columns, rows of inner corners); with
``cv2.CALIB_CB_LARGER`` it returns the largest grid it can extend from it."""


def checkerboard_grid(gray: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """The X-corners of the largest checkerboard in ``gray``, as a grid.

    The detector draws from OpenCV's random generator: it is seeded with ``seed`` and
    run on one thread (the setting restored after), so that one image gives one grid.

    Parameters
    ----------
    gray : (H, W) uint8
        The image, grey levels.
    seed : int
        Seed of OpenCV's generator for this call.

    Returns
    -------
    (R, C, 2) float array or None
        Corner (x, y) in pixels of ``gray``, ``[r, c]`` adjacent to ``[r, c + 1]`` and
        ``[r + 1, c]`` (R, C >= 3); None when no checkerboard of at least 3 x 3 corners
        is found.
    """
    g = np.ascontiguousarray(gray, np.uint8)
    if g.ndim != 2 or min(g.shape) < 16:
        return None
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        cv2.setRNGSeed(int(seed))
        ok, corners, meta = cv2.findChessboardCornersSBWithMeta(
            g, PROBE, cv2.CALIB_CB_LARGER | cv2.CALIB_CB_EXHAUSTIVE)
    finally:
        cv2.setNumThreads(threads)
    if not ok or corners is None or meta is None:
        return None
    rows, cols = meta.shape[:2]
    if rows * cols != len(corners):
        return None
    return corners.reshape(rows, cols, 2).astype(float)


def grid_outline(grid: np.ndarray, border: int) -> np.ndarray:
    """Outline of ``grid`` extended by ``border`` cells on every side.

    Each added row or column continues the grid linearly (the spacing of the last two;
    exact for a fronto-parallel board, close under perspective over a few cells).

    Parameters
    ----------
    grid : (R, C, 2) float, R, C >= 2
        Corner positions (:func:`checkerboard_grid`).
    border : int >= 0
        Cells added on every side.

    Returns
    -------
    (K, 2) float
        The extended grid's boundary corners in order around it, K = 2 (R' + C') - 4
        with R' = R + 2 border, C' = C + 2 border.

    >>> g = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0)), -1) * 10
    >>> o = grid_outline(g, 1)
    >>> o.shape, o.min(0).tolist(), o.max(0).tolist()
    ((16, 2), [-10.0, -10.0], [30.0, 30.0])
    """
    g = np.asarray(grid, float)
    if g.ndim != 3 or g.shape[0] < 2 or g.shape[1] < 2 or g.shape[2] != 2:
        raise ValueError(f"grid must be (R, C, 2) with R, C >= 2, got {g.shape}")
    for _ in range(int(border)):
        g = np.concatenate([2 * g[:1] - g[1:2], g, 2 * g[-1:] - g[-2:-1]], 0)
        g = np.concatenate([2 * g[:, :1] - g[:, 1:2], g, 2 * g[:, -1:] - g[:, -2:-1]], 1)
    return np.concatenate([g[0, :], g[1:, -1], g[-1, -2::-1], g[-2:0:-1, 0]])


def grid_cells(gray: np.ndarray, grid: np.ndarray) -> tuple[float, float]:
    """How much the cells of a corner grid look like a checkerboard's squares.

    Parameters
    ----------
    gray : (H, W) uint8
    grid : (R, C, 2) float, R, C >= 2 (:func:`checkerboard_grid`)

    Returns
    -------
    orientation : float in [0.5, 1]
        Share of the (R - 1)(C - 1) cells turned the majority's way (1: every cell a
        quadrilateral of one orientation, the grid folds nowhere).
    alternation : float in [0.5, 1]
        Share of the cells whose centre (the mean grey level over a box half the cell's
        side) lies on the side of the cells' median that a checkerboard's parity gives,
        the better of the two parities.

    >>> sq = 20
    >>> img = (((np.indices((6 * sq, 6 * sq)) // sq).sum(0) % 2) * 200 + 30).astype(np.uint8)
    >>> g = np.stack(np.meshgrid(np.arange(1, 6.0), np.arange(1, 6.0)), -1) * sq
    >>> grid_cells(img, g)
    (1.0, 1.0)
    >>> grid_cells(np.full_like(img, 90), g)[1] < 0.75
    True
    """
    g = np.asarray(grid, float)
    a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1]
    d1, d2 = c - a, d - b
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    orientation = float(max((cross > 0).mean(), (cross < 0).mean()))
    centre = (a + b + c + d) / 4
    half = np.sqrt(np.abs(cross) / 2) / 4
    h, w = gray.shape[:2]
    level = np.full(cross.shape, np.nan)
    for i in range(cross.shape[0]):
        for j in range(cross.shape[1]):
            x, y = centre[i, j]
            r = max(1, int(half[i, j]))
            x0, x1 = max(0, int(round(x)) - r), min(w, int(round(x)) + r + 1)
            y0, y1 = max(0, int(round(y)) - r), min(h, int(round(y)) + r + 1)
            if x0 < x1 and y0 < y1:
                level[i, j] = float(gray[y0:y1, x0:x1].mean())
    seen = np.isfinite(level)
    if not seen.any():
        return orientation, 0.5
    side = np.sign(level[seen] - np.median(level[seen]))
    parity = ((np.indices(level.shape).sum(0) % 2) * 2 - 1)[seen]
    return orientation, float(max((side == parity).mean(), (side == -parity).mean()))


def checkerboard_outline(gray: np.ndarray, min_corners: int, border: int, seed: int = 0,
                         min_alternation: float = 0.75) -> np.ndarray | None:
    """The board of the largest checkerboard in ``gray``: its corner grid
    (:func:`checkerboard_grid`, with ``seed``) extended by ``border`` cells
    (:func:`grid_outline`); None when there is none with at least ``min_corners``
    corners, or ``min_corners`` is 0 (off).

    A grid is a board only when it folds nowhere and its cells alternate like a
    checkerboard's (:func:`grid_cells`: orientation 1, alternation at least
    ``min_alternation``, which leaves room for pieces on a quarter of the squares): on
    facades and in streets the detector also strings together a few X-like corners of
    windows and bars, which fold or do not alternate.

    Parameters
    ----------
    gray : (H, W) uint8
    min_corners : int >= 0
    border : int >= 0
    seed : int
    min_alternation : float in [0.5, 1]

    Returns
    -------
    (K, 2) float or None
        Outline in pixels of ``gray``.
    """
    if min_corners <= 0:
        return None
    grid = checkerboard_grid(gray, seed)
    if grid is None or grid.shape[0] * grid.shape[1] < min_corners:
        return None
    orientation, alternation = grid_cells(gray, grid)
    if orientation < 1.0 or alternation < min_alternation:
        return None
    return grid_outline(grid, border)


def share_inside(boxes: np.ndarray, outline: np.ndarray) -> float:
    """Share of ``boxes`` whose centre lies inside (or on) the polygon ``outline``.

    Parameters
    ----------
    boxes : (N, 4) float, (x, y, w, h) in the outline's pixels
    outline : (K, 2) float, K >= 3

    Returns
    -------
    float in [0, 1]; 0 when there is no box.

    >>> sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    >>> share_inside(np.array([[2, 2, 2, 2], [20, 20, 2, 2]], float), sq)
    0.5
    """
    b = np.asarray(boxes, float).reshape(-1, 4)
    if not len(b):
        return 0.0
    poly = np.asarray(outline, np.float32).reshape(-1, 1, 2)
    ctr = b[:, :2] + b[:, 2:] / 2
    inside = [cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in ctr]
    return float(np.mean(inside))


def board_outline(rgb: np.ndarray, scale_factor: float, dp: BoardParams
                  ) -> np.ndarray | None:
    """Outline ((K, 2), original pixels) of the checkerboard in the prepared image
    ``rgb`` ((H, W, 3) uint8, processed = original x ``scale_factor``):
    :func:`checkerboard_outline` with the ``checkerboard_*`` fields of ``dp`` (a
    :class:`rescu.discovery.sources.DenseParams`); None when the test is off or no board
    is found."""
    if dp.checkerboard_min_corners <= 0:
        return None
    gray = cv2.cvtColor(np.ascontiguousarray(rgb, np.uint8), cv2.COLOR_RGB2GRAY)
    out = checkerboard_outline(gray, dp.checkerboard_min_corners, dp.checkerboard_border,
                               dp.checkerboard_seed, dp.checkerboard_min_alternation)
    return None if out is None else out / float(scale_factor)
