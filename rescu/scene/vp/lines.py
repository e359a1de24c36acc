"""Image lines of the VP estimators: :class:`Lines` and the implicit lines of an RP.

:func:`pattern_lines` fits one implicit line (total least squares) per visual word and
row of a recurring pattern; a row with no usable feature gives the line through its
instance centres. All coordinates are pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ...layout import checked_points, fit_line


@dataclass
class Lines:
    """A set of image lines (segments) in pixels.

    Attributes
    ----------
    midpoints : (L, 2) float
        A point on each line (segment midpoint / centroid of the fitted points), pixels.
    directions : (L, 2) float
        Unit direction of each line.
    weights : (L,) float
        Weight of each line in the support and the fit (1 for implicit lines, the
        length in pixels for segments).
    precision : (L,) float or None
        Extra weight of each line in the least-squares refinement only (inverse
        angular variance, relative); None: all 1.
    points : list of (K_l, 2) float arrays or None
        The image points each line was fitted to (pixels), for the maximum-likelihood
        refinement (:func:`rescu.scene.vp.refine.ml_refine_vp`); None: unknown (e.g. LSD segments).
    positions : list of (K_l,) float arrays or None entries, or None
        For a line fitted to the features of one visual word along an *equally spaced* row:
        the ordinal of each point's instance in the row (0, 1, 2, ...; gaps where the word
        is missing), used by the spacing model
        (:func:`rescu.scene.vp.refine.spacing_refine_vp`); None where the row is not known
        to be equally spaced.
    """

    midpoints: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    precision: np.ndarray | None = None
    points: list[np.ndarray] | None = None
    positions: list[np.ndarray | None] | None = None

    def __post_init__(self) -> None:
        self.midpoints = np.asarray(self.midpoints, float).reshape(-1, 2)
        self.directions = np.asarray(self.directions, float).reshape(-1, 2)
        n = len(self.midpoints)
        if self.directions.shape != (n, 2):
            raise ValueError(f"Lines.directions must have shape ({n}, 2), "
                             f"got {self.directions.shape}")
        self.weights = np.asarray(self.weights, float).reshape(-1)
        if self.weights.shape != (n,):
            raise ValueError(f"Lines.weights must have shape ({n},), got {self.weights.shape}")
        norm = np.linalg.norm(self.directions, axis=1, keepdims=True)
        self.directions = self.directions / np.where(norm > 0, norm, 1.0)
        self.precision = (np.ones(n) if self.precision is None
                          else np.asarray(self.precision, float).reshape(-1))
        if self.precision.shape != (n,):
            raise ValueError(f"Lines.precision must have shape ({n},), "
                             f"got {self.precision.shape}")
        if self.points is not None:
            if len(self.points) != n:
                raise ValueError(f"Lines.points must hold {n} arrays, got {len(self.points)}")
            self.points = [np.asarray(q, float).reshape(-1, 2) for q in self.points]
        if self.positions is not None:
            if self.points is None or len(self.positions) != n:
                raise ValueError(f"Lines.positions must hold {n} entries and needs points")
            self.positions = [None if k is None else np.asarray(k, float).reshape(-1)
                              for k in self.positions]
            for k, q in zip(self.positions, self.points):
                if k is not None and len(k) != len(q):
                    raise ValueError("Lines.positions: one ordinal per point")

    def __len__(self) -> int:
        return len(self.midpoints)

    @classmethod
    def empty(cls) -> "Lines":
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0,)))

    @classmethod
    def from_segments(cls, segments: np.ndarray) -> "Lines":
        """Lines from segments ``(L, 4)`` ``[x1, y1, x2, y2]`` pixels, weighted by length."""
        s = np.asarray(segments, float).reshape(-1, 4)
        d = s[:, 2:] - s[:, :2]
        return cls((s[:, :2] + s[:, 2:]) / 2, d, np.linalg.norm(d, axis=1))

    @classmethod
    def concat(cls, parts: Sequence["Lines"]) -> "Lines":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        pts = (None if any(p.points is None for p in parts)
               else [q for p in parts for q in p.points])
        pos = (None if pts is None or all(p.positions is None for p in parts)
               else [k for p in parts
                     for k in (p.positions if p.positions is not None else [None] * len(p))])
        return cls(np.concatenate([p.midpoints for p in parts]),
                   np.concatenate([p.directions for p in parts]),
                   np.concatenate([p.weights for p in parts]),
                   np.concatenate([p.precision for p in parts]), pts, pos)


def pattern_lines(feature_points: np.ndarray | None, centres: np.ndarray,
                  rows: Sequence[np.ndarray], sizes: np.ndarray | None = None,
                  max_line_residual: float = 0.15, precision_floor_px: float = 1.0,
                  equal_rows: Sequence[bool] | None = None) -> Lines:
    """Implicit lines of an RP: one per visual word and row.

    Parameters
    ----------
    feature_points : (M, N', 2) float or None
        Corresponding feature positions, pixels, NaN where missing; column n belongs to
        instance n (N' may be smaller than the number of instances N: the later
        instances have no features).
    centres : (N, 2) float
        Instance centres, pixels.
    rows : list of int arrays
        Instance indices of each row, from :func:`rescu.layout.group_rows`.
    sizes : (N,) float or None
        Instance sizes, pixels (for the residual check; None: no check).
    max_line_residual : float
        Lines with RMS residual above this fraction of the median row instance size are
        dropped.
    precision_floor_px : float
        Noise floor (pixels) of the line precision weights of the refinement
        (:func:`_line_precision`); 0 gives all lines the same weight.
    equal_rows : list of bool or None
        Per row, whether it is equally spaced in 3D (translation symmetry): its feature
        lines then carry the instance ordinals of their points (``Lines.positions``).

    Returns
    -------
    Lines
        A word needs a finite point in at least min(3, row length) instances of the row.
        A row without any feature line gives the line through its instance centres.
    """
    c, fp = checked_points(centres, feature_points)
    mids, dirs, prec = [], [], []
    pts_used: list[np.ndarray] = []
    pos_used: list[np.ndarray | None] = []
    if equal_rows is not None and len(equal_rows) != len(rows):
        raise ValueError(f"equal_rows must have {len(rows)} entries, got {len(equal_rows)}")
    for r_i, row in enumerate(rows):
        row = np.asarray(row, int)
        equal = bool(equal_rows[r_i]) if equal_rows is not None else False
        need = min(3, len(row))
        scale = float(np.median(sizes[row])) if sizes is not None else np.inf
        got = 0
        if fp is not None and len(row) >= 2:
            pts = fp[:, row, :]  # (M, K, 2)
            fin = np.all(np.isfinite(pts), axis=2)
            for m in range(pts.shape[0]):
                q = pts[m][fin[m]]
                if len(q) < need:
                    continue
                if np.linalg.norm(q.max(axis=0) - q.min(axis=0)) <= 0:
                    continue
                cen, d, rms = fit_line(q)
                if rms > max_line_residual * scale:
                    continue
                mids.append(cen)
                dirs.append(d)
                prec.append(_line_precision(q, cen, d, rms, precision_floor_px))
                pts_used.append(q)
                pos_used.append(np.nonzero(fin[m])[0].astype(float) if equal else None)
                got += 1
        if got == 0 and len(row) >= 2:
            cen, d, rms = fit_line(c[row])
            if rms <= max_line_residual * scale or len(row) == 2:
                mids.append(cen)
                dirs.append(d)
                prec.append(_line_precision(c[row], cen, d, rms, precision_floor_px))
                pts_used.append(c[row])
                pos_used.append(np.arange(len(row), dtype=float) if equal else None)
    if not mids:
        return Lines.empty()
    p = np.array(prec)
    return Lines(np.array(mids), np.array(dirs), np.ones(len(mids)), p / p.mean(),
                 pts_used, pos_used if any(k is not None for k in pos_used) else None)


def _line_precision(q: np.ndarray, cen: np.ndarray, d: np.ndarray, rms: float,
                    floor_px: float) -> float:
    """Inverse angular variance of a TLS line: sum of squared spreads / noise variance.

    The noise is the RMS residual (floored at ``floor_px``); var(angle) ~ sigma^2 /
    sum_k ((q_k - centroid) . d)^2.
    """
    if floor_px <= 0:
        return 1.0
    t = (q - cen) @ d
    return float((t ** 2).sum() / max(rms, floor_px) ** 2)
