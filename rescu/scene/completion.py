"""Row and grid completion: fill gaps of equally spaced rows and empty cells of grids.

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
* the model is a valid projective row over the span (``c k + 1 > 0``) whose image steps
  between consecutive lattice points over the whole span (end extensions included) are
  within a factor ``max_step_ratio`` of each other (longest / shortest),
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
:func:`rescu.scene.symmetry.cross_ratio`). An empty background gap has NCC near 0.

Grids
-----
After the rows, an RP of two or more rows (:func:`rescu.layout.pattern_rows` with rows of
two or more instances, ordered across) is completed as a grid, one pair of neighbouring
rows at a time: :func:`rescu.scene.lattice.lattice_pair_fit` finds the projective
lattice (a homography from integer cells (u, v), v = 0 / 1 for the two rows) that puts
most instances on cells, allowing empty cells between found instances and limiting the
perspective by ``max_step_ratio``; :func:`rescu.scene.lattice.grid_missing_cells` lists
the empty cells of the rectangle the two rows span (the column alignment of two rows is
known up to a shift; the shifts leaving fewest empty cells are tried). Each empty cell,
at most ``grid_max_missing`` per row pair, gets a box of the row's median size scaled
by the local lattice step and is verified by NCC as above. The lattice assumes rows and
columns equally spaced in 3D (found instances may leave empty cells between them, up to
``max_gaps``); grids with unequal spacing get no fit and are left as they are. Instance
positions are registered by their features (:func:`rescu.layout.registered_centres`).

Accepted candidates become instances with ``source = "completion"`` and ``score`` = their
median NCC. They are appended after the existing instances (the columns of
``feature_points`` keep belonging to the first instances) and ``extra["completed_rows"]``
of the pattern lists each completed row's instance indices in order along the row, filled
gaps included (the scene step's own ``extra["rows"]`` are the rows its VP and TS used).
All boxes are original pixels; the image is the processed one (original x
``scale_factor``).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .. import layout as L
from . import symmetry as S
from .lattice import (OFF_LATTICE, cell_wh, fit_projective_row, gap_hypotheses,
                      grid_missing_cells, lattice_map, lattice_pair_fit, lattice_step,
                      row_model, steps_ok)
from .vp.params import VPParams
from ..params import config_section, params_from_dict
from ..types import ImageResult, Instance, Pattern

SOURCE = "completion"


@dataclass(frozen=True)
@config_section("scene", "completion")
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
        Perspective limit: largest ratio of the longest to the shortest image step of
        the model over a row's span (grids: over the lattice rectangle of two rows, both
        rows); a 3-instance row whose two steps are within this ratio counts as already
        complete.
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
    grid : bool
        Grid completion after row completion (see module docstring): cells of a
        projective lattice spanned by two neighbouring rows that have no instance.
    grid_tolerance : float
        An instance lies on a lattice cell when its centre is within this fraction of
        the median instance size of the two rows of the cell's image position.
    grid_max_missing : int
        A pair of rows with more empty cells than this (under its best column
        alignment) is not completed: only nearly complete grids are filled.
    """

    enabled: bool
    max_gaps: int
    cr_tolerance: float
    fit_tolerance: float
    max_step_ratio: float
    similarity_ratio: float
    min_similarity: float
    search_radius: float
    search_step_px: float
    patch_size: int
    min_row_instances: int
    end_instances: int
    grid: bool
    grid_tolerance: float
    grid_max_missing: int

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "CompletionParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


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


def _acceptance(tmpl: list[np.ndarray], params: CompletionParams
                ) -> tuple[float, np.ndarray] | None:
    """(NCC threshold, mean instance crop) for candidates of a row or grid, from the
    instances' crops (module docstring); None with fewer than two crops or when the
    instances do not correlate with each other (median pair NCC <= 0)."""
    if len(tmpl) < 2:
        return None
    base = _median_pair_ncc(tmpl)
    if not np.isfinite(base) or base <= 0:
        return None
    return max(params.min_similarity, params.similarity_ratio * base), np.mean(tmpl, axis=0)


# ----------------------------------------------------------------------------- main
def complete_rows(result: ImageResult, gray: np.ndarray,
                  params: CompletionParams = CompletionParams(),
                  scale_factor: float = 1.0,
                  vp_params: VPParams = VPParams()) -> ImageResult:
    """Complete the rows and grids of every pattern (see module docstring).

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
        as the scene step uses it (:func:`rescu.layout.pattern_rows`).

    Returns
    -------
    ImageResult
        A copy; ``result`` is not modified. Patterns with filled gaps get instances with
        ``source="completion"`` appended and ``extra["completed_rows"]`` set (every row,
        completed ones with their new instances; grid cells are appended after them);
        every pattern gets ``extra["completed"]``
        (number of instances added) and ``extra["grid_completed"]`` (of those, by grid
        completion).
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
                      vp_params: VPParams) -> Pattern:
    n = p.count
    if n < params.min_row_instances:
        p.extra["completed"] = p.extra["grid_completed"] = 0
        return p
    boxes = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    fp = None if p.feature_points is None else np.asarray(p.feature_points, float)
    if fp is not None and (fp.ndim != 3 or fp.shape[1] > n):
        fp = None
    c, sz, rows = L.pattern_rows(boxes, fp, vp_params)
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
    if added:
        p.instances = list(p.instances) + added
        p.extra["completed_rows"] = new_rows
    grid_added = _complete_grid(p, gray, params, sf, vp_params) if params.grid else []
    if grid_added:
        p.instances = list(p.instances) + grid_added
    p.extra["completed"] = len(added) + len(grid_added)
    p.extra["grid_completed"] = len(grid_added)
    return p


def _complete_row(r: np.ndarray, c: np.ndarray, boxes: np.ndarray, fp: np.ndarray | None,
                  gray: np.ndarray, params: CompletionParams, sf: float,
                  sym: S.SymmetryParams) -> list[Any] | None:
    """The completed row (instance indices and new Instances in order) or None."""
    if len(r) < params.min_row_instances:
        return None
    pts = c[r]
    cen, d, _ = L.fit_line(pts)
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
    gate = _acceptance(tmpl, params)
    if gate is None:
        return None
    thr, mean_t = gate
    if equal:
        return _extend_ends(r, pts, t, perp, wh, c, cen, d, nrm, size, gray, tmpl, mean_t,
                            thr, params, sf)
    for k in gap_hypotheses(len(r), params.max_gaps):
        abc, rms = fit_projective_row(k, t)
        if len(r) >= 4 and rms > params.fit_tolerance * size:
            continue
        if not np.isfinite(rms) or not steps_ok(abc, 0, int(k[-1]), params.max_step_ratio):
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
            if not steps_ok(abc, min(km, 0), max(km, n - 1), params.max_step_ratio):
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


# ----------------------------------------------------------------------------- grids
def _complete_grid(p: Pattern, gray: np.ndarray, params: CompletionParams, sf: float,
                   vp_params: VPParams) -> list[Instance]:
    """Instances for the empty cells of grids of two or more rows (module docstring)."""
    boxes = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    if len(boxes) < 4:
        return []
    fp = None if p.feature_points is None else np.asarray(p.feature_points, float)
    if fp is not None and (fp.ndim != 3 or fp.shape[1] > len(boxes)):
        fp = None
    # registered centres (partial boxes: instances located by their features), rows of
    # two or more instances
    c, sz, rows = L.pattern_rows(boxes, fp, dataclasses.replace(vp_params, min_row_instances=2))
    if np.any(sz <= 0):
        return []
    rows = [np.asarray(r, int) for r in rows if len(r) >= 2]
    if len(rows) < 2:
        return []
    dirs = [L.fit_line(c[r])[1] for r in rows]
    d0 = dirs[0]
    dm = np.sum([d if d @ d0 >= 0 else -d for d in dirs], axis=0)
    dm /= np.linalg.norm(dm)
    nrm = np.array([-dm[1], dm[0]])
    rows = [rows[i] for i in np.argsort([float(np.mean(c[r] @ nrm)) for r in rows],
                                        kind="stable")]
    rows = [r[np.argsort(c[r] @ dm, kind="stable")] for r in rows]
    new: list[Instance] = []
    cen = [q for q in c]                       # registered centres and added instances
    cb0 = boxes[:, :2] + boxes[:, 2:] / 2      # box centres
    for ra, rb in zip(rows[:-1], rows[1:]):
        # tolerance from the rows' median size: stage-I boxes of partial instances are small
        tol = params.grid_tolerance * float(np.median(sz[np.r_[ra, rb]]))
        fit = lattice_pair_fit(c[ra], c[rb], np.full(len(ra), tol), np.full(len(rb), tol),
                               params.max_gaps + 1, params.max_step_ratio)
        if fit is None:
            continue
        Hm, ua, ub = fit
        cells = grid_missing_cells(ua[ua != OFF_LATTICE], ub[ub != OFF_LATTICE],
                                   params.grid_max_missing)
        if not cells:
            continue
        inl = [(i, int(u), 0) for i, u in zip(ra, ua) if u != OFF_LATTICE]
        inl += [(i, int(u), 1) for i, u in zip(rb, ub) if u != OFF_LATTICE]
        # box size per cell: the row's median box, scaled by the local lattice step
        # (stage-I boxes of partial instances are smaller than the object)
        wh_step = []  # per row: median box (w, h) and median lattice step, pixels
        for v in (0, 1):
            iv = [(i, u) for i, u, vv in inl if vv == v]
            wh_step.append((np.median(boxes[[i for i, _ in iv], 2:], axis=0),
                            float(np.median([lattice_step(Hm, u, v) for _, u in iv]))))
        tmpl = []
        for i, u, v in inl:
            w, h = cell_wh(Hm, wh_step[v], u, v)
            q = _crop(gray, c[i, 0] * sf, c[i, 1] * sf, w * sf, h * sf, params.patch_size)
            if q is not None:
                tmpl.append(q)
        gate = _acceptance(tmpl, params)
        if gate is None:
            continue
        thr, mean_t = gate
        for u, v in cells:
            xy = lattice_map(Hm, np.array([[u, v]], float))[0]
            if not np.all(np.isfinite(xy)):
                continue
            w, h = cell_wh(Hm, wh_step[v], u, v)
            if not np.isfinite(w * h):
                continue
            # perspective limit: the cell's step within max_step_ratio of the row's steps
            st = [lattice_step(Hm, u, v)] + [lattice_step(Hm, t[1], v) for t in inl
                                               if t[2] == v]
            if max(st) > params.max_step_ratio * min(st):
                continue
            near = 0.5 * lattice_step(Hm, u, v)  # instances do not overlap
            if min(w, h) < 2 or min(np.min(np.linalg.norm(np.array(cen) - xy, axis=1)),
                                    np.min(np.linalg.norm(cb0 - xy, axis=1))) < near:
                continue  # an instance (of any row) is already there
            got = _verify(gray, xy, float(w), float(h), tmpl, mean_t, thr, params, sf)
            if got is None:
                continue
            q, w, h, sim = got
            new.append(Instance(bbox=(float(q[0] - w / 2), float(q[1] - h / 2), float(w),
                                      float(h)), score=float(np.clip(sim, 0.0, 1.0)),
                                source=SOURCE))
            cen.append(q)
    return new
