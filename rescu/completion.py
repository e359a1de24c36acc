"""Row completion from 3D equal spacing: fill interior gaps of equally spaced rows.

An RP of identical objects in a row often misses one instance inside the row (occluded
by a thin line, blurred): the count is one short and the gap breaks the cross-ratio
test of 3D translation symmetry. :func:`complete_rows` hypothesises such gaps and
verifies each on the image.

Model
-----
Instances equally spaced in 3D along a line project to positions along the image row
(1D projective map of the integer lattice)::

    t(k) = (a k + b) / (c k + 1),     k = 0, 1, 2, ...

For a row of found instances (positions ``t_i`` along the fitted row line, ordered) a
*gap hypothesis* assigns increasing lattice indices ``k_i`` with one or more integers
skipped between two found instances (interior gaps only). ``a, b, c`` are fitted by
linear least squares (``a k + b - c k t = t``). A hypothesis is kept when

* the found positions fit the model within ``fit_tolerance`` x instance size (RMS),
* the model is a valid projective row over the span (``c k + 1 > 0``) whose image step
  between consecutive lattice points changes by at most ``max_step_ratio``,
* the row without the gap does not already pass the translation-symmetry (TS) test (4
  or more found instances), resp. does not already look evenly stepped (3 instances:
  step ratio <= ``max_step_ratio``),
* the completed row has >= 4 points.

Verification on the image
-------------------------
The missing instance's centre is the model position along the row, its perpendicular
offset and its box size interpolated from the two neighbours. The grey crops of the
row's instances and of the candidate are resized to a common size and compared by
normalised cross-correlation (NCC); the candidate is moved by up to ``search_radius``
x its size (step ``search_step_px``) to the position of highest mean NCC to the
instances. It is accepted when its median NCC to the row instances is at least
``similarity_ratio`` x the median instance-to-instance NCC and at least
``min_similarity``, and when, at the refined position, every 4 consecutive points of the
completed row give ``|cr - 4/3| <= cr_tolerance`` (the TS test's t; cr = cross ratio,
:func:`rescu.symmetry.cross_ratio`). An empty background gap has NCC near 0.

Accepted candidates become instances with ``source = "completion"`` and ``score`` = their
median NCC. They are appended after the existing instances (the columns of
``feature_points`` keep belonging to the first instances) and ``extra["rows"]`` of the
pattern lists each row's instance indices in order along the row, filled gaps included.
All boxes are original pixels; the image is the processed one (original x
``scale_factor``).
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from . import symmetry as S
from . import vp as V
from .params import params_from_dict
from .types import ImageResult, Instance, Pattern

SOURCE = "completion"


@dataclass(frozen=True)
class CompletionParams:
    """Parameters of row completion (config section ``completion``).

    Attributes
    ----------
    enabled : bool
        Off: :func:`complete_rows` returns an unchanged copy.
    max_gaps : int
        Most missing instances filled per row.
    cr_tolerance : float
        t of the cross-ratio check of the completed row, ``|cr - 4/3| <= t``.
    fit_tolerance : float
        Largest RMS residual of the found positions to the projective row model, as a
        fraction of the median instance size.
    max_step_ratio : float
        Largest ratio of consecutive image steps of the model (perspective limit); a
        3-instance row whose two steps are within this ratio counts as already complete.
    similarity_ratio : float
        Candidate accepted when its median NCC to the row instances >= this x the median
        instance-to-instance NCC.
    min_similarity : float
        Absolute floor of the candidate's median NCC.
    search_radius : float
        Local search for the candidate position, fraction of the instance size.
    search_step_px : float
        Step of the local search, processed pixels.
    patch_size : int
        Side of the common size crops are resized to, pixels.
    min_row_instances : int
        Fewest found instances in a row for completion (>= 3).
    end_instances : int
        Row ends: an already equally spaced row (no interior gap) is extended by up to
        this many lattice steps beyond each end, each verified like a gap (0 = off).
    """

    enabled: bool = True
    max_gaps: int = 2
    cr_tolerance: float = 0.06
    fit_tolerance: float = 0.05
    max_step_ratio: float = 1.5
    similarity_ratio: float = 0.75
    min_similarity: float = 0.5
    search_radius: float = 0.15
    search_step_px: float = 1.0
    patch_size: int = 24
    min_row_instances: int = 3
    end_instances: int = 1

    def __post_init__(self) -> None:
        if self.max_gaps < 1:
            raise ValueError("CompletionParams.max_gaps must be >= 1")
        if self.cr_tolerance < 0 or self.fit_tolerance < 0:
            raise ValueError("CompletionParams.cr_tolerance and fit_tolerance must be >= 0")
        if self.max_step_ratio < 1:
            raise ValueError("CompletionParams.max_step_ratio must be >= 1")
        if not 0 <= self.similarity_ratio <= 1:
            raise ValueError("CompletionParams.similarity_ratio must be in [0, 1]")
        if not -1 <= self.min_similarity <= 1:
            raise ValueError("CompletionParams.min_similarity must be in [-1, 1]")
        if self.search_radius < 0 or self.search_step_px <= 0:
            raise ValueError("CompletionParams.search_radius must be >= 0 and "
                             "search_step_px > 0")
        if self.patch_size < 4:
            raise ValueError("CompletionParams.patch_size must be >= 4")
        if self.end_instances < 0:
            raise ValueError("CompletionParams.end_instances must be >= 0")
        if self.min_row_instances < 3:
            raise ValueError("CompletionParams.min_row_instances must be >= 3")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "CompletionParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


# ----------------------------------------------------------------------------- model
def fit_projective_row(k: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares 1D projective row ``t = (a k + b) / (c k + 1)``.

    Parameters
    ----------
    k : (K,) float
        Lattice indices (K >= 3).
    t : (K,) float
        Positions along the row, pixels.

    Returns
    -------
    abc : (3,) float
        ``(a, b, c)``.
    rms : float
        RMS residual of ``t``, pixels (inf when the model is singular at some k).
    """
    k = np.asarray(k, float).reshape(-1)
    t = np.asarray(t, float).reshape(-1)
    if k.shape != t.shape or len(k) < 3:
        raise ValueError(f"k and t must have the same shape (K,), K >= 3; got {k.shape}, "
                         f"{t.shape}")
    # a k + b - c k t = t  (linear in a, b, c)
    A = np.stack([k, np.ones_like(k), -k * t], axis=1)
    abc = np.linalg.lstsq(A, t, rcond=None)[0]
    den = abc[2] * k + 1
    if np.any(np.abs(den) < 1e-9):
        return abc, float("inf")
    return abc, float(np.sqrt(np.mean((row_model(abc, k) - t) ** 2)))


def row_model(abc: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Positions ``(a k + b) / (c k + 1)`` of lattice indices k (pixels)."""
    a, b, c = abc
    k = np.asarray(k, float)
    return (a * k + b) / (c * k + 1)


def gap_hypotheses(n: int, max_gaps: int) -> list[np.ndarray]:
    """Lattice indices of n found instances with 1..max_gaps interior integers skipped.

    Returns
    -------
    list of (n,) int arrays
        ``k`` with ``k[0] = 0``, increasing; fewer gaps first, then lexicographic.
    """
    out = []
    for g in range(1, max_gaps + 1):
        for combo in itertools.combinations_with_replacement(range(n - 1), g):
            steps = np.ones(n - 1, int)
            for j in combo:
                steps[j] += 1
            out.append(np.concatenate([[0], np.cumsum(steps)]))
    return out


def _steps_ok(abc: np.ndarray, k_lo: int, k_hi: int, max_step_ratio: float) -> bool:
    """The row model is defined, increasing, and its image steps between lattice indices
    k_lo..k_hi change by at most a factor ``max_step_ratio``."""
    ks = np.arange(k_lo, k_hi + 1, dtype=float)
    den = abc[2] * ks + 1
    if np.any(den <= 1e-9):
        return False
    st = np.diff(row_model(abc, ks))
    if np.any(st <= 0):
        return False
    return bool(st.max() / st.min() <= max_step_ratio)


# ----------------------------------------------------------------------------- image
def _crop(gray: np.ndarray, cx: float, cy: float, w: float, h: float,
          size: int) -> np.ndarray | None:
    """Zero-mean unit-norm crop (size*size) of the box centred at (cx, cy); None when
    the box leaves the image or is flat."""
    H, W = gray.shape
    x0, y0, x1, y1 = cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2
    if x0 < 0 or y0 < 0 or x1 > W or y1 > H or w < 2 or h < 2:
        return None
    # affine map of the box onto the patch (sub-pixel, bilinear)
    sx, sy = w / size, h / size
    M = np.array([[sx, 0, x0 + 0.5 * sx - 0.5], [0, sy, y0 + 0.5 * sy - 0.5]])
    p = cv2.warpAffine(gray, M, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    p -= p.mean()
    n = np.linalg.norm(p)
    if n < 1e-6 * size:
        return None
    return p / n


def _median_pair_ncc(patches: list[np.ndarray]) -> float:
    v = [float((patches[i] * patches[j]).sum())
         for i in range(len(patches)) for j in range(i + 1, len(patches))]
    return float(np.median(v)) if v else float("nan")


# ----------------------------------------------------------------------------- main
def complete_rows(result: ImageResult, gray: np.ndarray,
                  params: CompletionParams = CompletionParams(),
                  scale_factor: float = 1.0,
                  vp_params: V.VPParams = V.VPParams()) -> ImageResult:
    """Fill interior gaps of equally spaced rows of every pattern (see module docstring).

    Parameters
    ----------
    result : ImageResult
        Stage I / II result, boxes in original pixels.
    gray : (H, W) float or uint8
        The processed grey image (original x ``scale_factor``).
    params : CompletionParams
    scale_factor : float
        processed = original * scale_factor.
    vp_params : VPParams
        Row grouping (``row_tolerance``, ``min_row_instances``, ``register_centres``),
        as the scene step uses it (:func:`rescu.vp.pattern_rows`).

    Returns
    -------
    ImageResult
        A copy; ``result`` is not modified. Patterns with filled gaps get instances with
        ``source="completion"`` appended and ``extra["rows"]`` set; every pattern gets
        ``extra["completed"]`` (number of instances added).
    """
    if not isinstance(result, ImageResult):
        raise TypeError(f"result must be an ImageResult, got {type(result).__name__}")
    g = np.asarray(gray)
    if g.ndim != 2:
        raise ValueError(f"gray must have shape (H, W), got {g.shape}")
    if not scale_factor > 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    res = copy.deepcopy(result)
    if not params.enabled:
        return res
    g = g.astype(np.float32)
    res.patterns = [_complete_pattern(p, g, params, float(scale_factor), vp_params)
                    for p in res.patterns]
    return res


def _complete_pattern(p: Pattern, gray: np.ndarray, params: CompletionParams, sf: float,
                      vp_params: V.VPParams) -> Pattern:
    n = p.count
    if n < params.min_row_instances:
        return p
    boxes = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    fp = None if p.feature_points is None else np.asarray(p.feature_points, float)
    if fp is not None and (fp.ndim != 3 or fp.shape[1] > n):
        fp = None
    c, sz, rows = V.pattern_rows(boxes, fp, vp_params)
    sym = S.SymmetryParams(threshold=params.cr_tolerance)
    new_rows: list[list[int]] = []
    added: list[Instance] = []
    for r in rows:
        r = np.asarray(r, int)
        filled = _complete_row(r, c, boxes, fp, gray, params, sf, sym)
        if filled is None:
            new_rows.append([int(i) for i in r])
            continue
        row_ids: list[int] = []
        for item in filled:
            if isinstance(item, Instance):
                row_ids.append(n + len(added))
                added.append(item)
            else:
                row_ids.append(int(item))
        new_rows.append(row_ids)
    p.extra["completed"] = len(added)
    if added:
        p.instances = list(p.instances) + added
        p.extra["rows"] = new_rows
    return p


def _complete_row(r: np.ndarray, c: np.ndarray, boxes: np.ndarray, fp: np.ndarray | None,
                  gray: np.ndarray, params: CompletionParams, sf: float,
                  sym: S.SymmetryParams) -> list[Any] | None:
    """The completed row (instance indices and new Instances in order) or None."""
    if len(r) < params.min_row_instances:
        return None
    pts = c[r]
    cen, d, _ = V.fit_line(pts)
    t = (pts - cen) @ d
    order = np.argsort(t, kind="stable")
    r, pts, t = r[order], pts[order], t[order]
    nrm = np.array([-d[1], d[0]])
    perp = (pts - cen) @ nrm
    wh = boxes[r, 2:]
    size = float(np.median(np.minimum(wh[:, 0], wh[:, 1])))
    steps = np.diff(t)
    if np.any(steps <= 1e-9):  # coincident instances: no row model
        return None
    # the row without gaps already equally spaced?
    if len(r) >= 4:
        ts = S.translation_symmetry(None, c, [r], sym)
        equal = ts is not None and ts.detected
    else:
        equal = bool(steps.max() / steps.min() <= params.max_step_ratio)
    if equal and params.end_instances == 0:
        return None
    # instance crops (processed pixels) at a common size, centred at the row positions
    tmpl = []
    for i, q in zip(r, pts):
        pc = _crop(gray, q[0] * sf, q[1] * sf, boxes[i, 2] * sf, boxes[i, 3] * sf,
                   params.patch_size)
        if pc is not None:
            tmpl.append(pc)
    if len(tmpl) < 2:
        return None
    base = _median_pair_ncc(tmpl)
    if not np.isfinite(base) or base <= 0:
        return None
    thr = max(params.min_similarity, params.similarity_ratio * base)
    mean_t = np.mean(tmpl, axis=0)
    if equal:
        return _extend_ends(r, pts, t, perp, wh, c, cen, d, nrm, size, gray, tmpl, mean_t,
                            thr, params, sf)
    for k in gap_hypotheses(len(r), params.max_gaps):
        abc, rms = fit_projective_row(k, t)
        if len(r) >= 4 and rms > params.fit_tolerance * size:
            continue
        if not np.isfinite(rms) or not _steps_ok(abc, 0, int(k[-1]), params.max_step_ratio):
            continue
        missing = np.setdiff1d(np.arange(k[-1] + 1), k)
        cands = []
        for km in missing:
            j = int(np.searchsorted(k, km))  # neighbours j-1, j
            tm = float(row_model(abc, [km])[0])
            lam = (tm - t[j - 1]) / (t[j] - t[j - 1])
            if not 0 < lam < 1:
                break
            off = (1 - lam) * perp[j - 1] + lam * perp[j]
            w, h = (1 - lam) * wh[j - 1] + lam * wh[j]
            xy = cen + tm * d + off * nrm
            if np.min(np.linalg.norm(c - xy, axis=1)) < 0.5 * size:
                break  # an instance of the pattern (maybe of another row) is there
            got = _verify(gray, xy, w, h, tmpl, mean_t, thr, params, sf)
            if got is None:
                break
            cands.append((km, got))
        else:
            # cross ratios of the completed row at the refined positions
            kk = np.concatenate([k, [km for km, _ in cands]])
            allp = np.concatenate([pts, np.array([x[0] for _, x in cands])])
            o = np.argsort(kk)
            crs = S.row_cross_ratios(allp[o])
            if len(crs) == 0 or not np.all(np.abs(crs - S.CR_EQUAL_SPACING)
                                           <= params.cr_tolerance):
                continue
            items: list[Any] = [int(i) for i in r]
            for km, (xy, w, h, sim) in cands:
                inst = Instance(bbox=(float(xy[0] - w / 2), float(xy[1] - h / 2),
                                      float(w), float(h)),
                                score=float(np.clip(sim, 0.0, 1.0)), source=SOURCE)
                items.append(inst)
            return [items[i] for i in o]
    return None


def _verify(gray: np.ndarray, xy: np.ndarray, w: float, h: float, tmpl: list[np.ndarray],
            mean_t: np.ndarray, thr: float, params: CompletionParams, sf: float
            ) -> tuple[np.ndarray, float, float, float] | None:
    """Refine the candidate by local search (highest NCC to the mean instance crop);
    (xy original pixels, w, h, median NCC) when it looks like the instances, else None."""
    rad = params.search_radius * min(w, h) * sf
    n = int(np.floor(rad / params.search_step_px))
    offs = np.arange(-n, n + 1) * params.search_step_px
    best = None
    for dy in offs:
        for dx in offs:
            pc = _crop(gray, xy[0] * sf + dx, xy[1] * sf + dy, w * sf, h * sf,
                       params.patch_size)
            if pc is None:
                continue
            s = float((pc * mean_t).sum())
            key = (s, -abs(dx) - abs(dy))
            if best is None or key > best[0]:
                best = (key, dx, dy, pc)
    if best is None:
        return None
    _, dx, dy, pc = best
    sim = float(np.median([(pc * q).sum() for q in tmpl]))
    if sim < thr:
        return None
    return np.array([xy[0] + dx / sf, xy[1] + dy / sf]), float(w), float(h), sim


def _extend_ends(r: np.ndarray, pts: np.ndarray, t: np.ndarray, perp: np.ndarray,
                 wh: np.ndarray, c: np.ndarray, cen: np.ndarray, d: np.ndarray,
                 nrm: np.ndarray, size: float, gray: np.ndarray, tmpl: list[np.ndarray],
                 mean_t: np.ndarray, thr: float, params: CompletionParams, sf: float
                 ) -> list[Any] | None:
    """Extend an equally spaced row beyond its ends by the projective row model (k = -1,
    -2, ... and K, K + 1, ...); perpendicular offset and size extrapolated linearly from
    the two end instances. None when nothing was added."""
    n = len(r)
    k = np.arange(n)
    abc, rms = fit_projective_row(k, t)
    if not np.isfinite(rms) or rms > params.fit_tolerance * size:
        return None
    items: list[Any] = [int(i) for i in r]
    allp = [p for p in pts]
    for side in (-1, 1):
        j0, j1 = (0, 1) if side < 0 else (n - 1, n - 2)
        for m in range(1, params.end_instances + 1):
            km = -m if side < 0 else n - 1 + m
            if not _steps_ok(abc, min(km, 0), max(km, n - 1), params.max_step_ratio):
                break
            tm = float(row_model(abc, [km])[0])
            lam = (tm - t[j0]) / (t[j1] - t[j0])  # < 0: beyond the end
            off = (1 - lam) * perp[j0] + lam * perp[j1]
            w, h = (1 - lam) * wh[j0] + lam * wh[j1]
            if w <= 1 or h <= 1:
                break
            xy = cen + tm * d + off * nrm
            if np.min(np.linalg.norm(c - xy, axis=1)) < 0.5 * size:
                break
            got = _verify(gray, xy, w, h, tmpl, mean_t, thr, params, sf)
            if got is None:
                break
            q = got[0]
            # cross ratio of the 4 points at this end, at the refined position
            seq = ([q] + allp[:3]) if side < 0 else (allp[-3:] + [q])
            cr = float(S.row_cross_ratios(np.array(seq))[0])
            if not abs(cr - S.CR_EQUAL_SPACING) <= params.cr_tolerance:
                break
            inst = Instance(bbox=(float(q[0] - w / 2), float(q[1] - h / 2), float(w),
                                  float(h)), score=float(np.clip(got[3], 0.0, 1.0)),
                            source=SOURCE)
            if side < 0:
                items.insert(0, inst)
                allp.insert(0, q)
            else:
                items.append(inst)
                allp.append(q)
    if len(items) == n:
        return None
    return items
