"""Diagnostics the benchmarks print, no table of a run: why counts are wrong, which truth
instance a box is, where instance precision goes, how precise each RP is on its own, and
whether stage II's split-RP merge is right on an image.

Only the benchmark scripts use them, so they live beside them (``benchmarks/`` is on a
script's path, as for ``_cli.py``: ``from _diagnostics import count_errors``); the
library and its tables never import this module.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from rescu.io import GroundTruthRP
from rescu.types import ImageResult
from rescu.evaluation.core import _load
from rescu.evaluation.count_table import _score_counting
from rescu.evaluation.metrics import IOD_H, MIN_RP_PRECISION, iod_matrix, match_boxes, score_image

if TYPE_CHECKING:     # imported where used: the evaluation rules never read stage II's code
    from rescu.extension.merge import MergeParams


def truth_instance_at(instances: Iterable[Mapping[str, Any]], box: Sequence[float]
                      ) -> Mapping[str, Any] | None:
    """The synthetic truth record (``truth.json``: ``center``, ``row``, ``col``,
    ``occluded_fraction``, ...) of the instance in ``box``.

    Parameters
    ----------
    instances : iterable of dict
        Truth instance records; ``center`` is ``[x, y]`` in pixels.
    box : sequence of 4 float
        ``(x, y, w, h)`` in pixels.

    Returns
    -------
    dict or None
        The first record whose centre lies within half the box's larger side of the box
        centre; None when none does (or ``box`` / a record has no finite centre).
    """
    b = np.asarray(box, float).reshape(4)
    c = b[:2] + b[2:] / 2
    for t in instances:
        if not isinstance(t, Mapping):
            continue
        tc = np.asarray(t.get("center", [np.nan, np.nan]), float).reshape(-1)[:2]
        if np.linalg.norm(tc - c) <= 0.5 * max(b[2], b[3]):
            return t
    return None


def count_errors(dataset_dir: str | Path, pred_dir: str | Path, h: float = IOD_H,
                 min_rp_precision: float = MIN_RP_PRECISION,
                 images: Iterable[str] | None = None) -> pd.DataFrame:
    """Why counts are wrong: the instances of every miscounted ground-truth RP.

    For each GT RP counted by a detected RP (as in :func:`count_frame`: the accepted
    detected RP with the most instances) whose count differs from the GT count, one row
    per GT instance (``kind`` "matched" or "missed", IOD > ``h`` one-to-one matching
    against that detected RP) and one per detected instance matching none of them
    (``kind`` "extra", with its ``source``: stage1 / stage2 / completion).

    Returns
    -------
    DataFrame
        ``image, gt_rp, pattern, det_count, gt_count, kind, x, y, w, h`` (box, pixels),
        ``source`` (extra rows), and where the dataset has ``truth.json`` (synthetic
        benchmark) ``row, col, occluded_fraction, blur_sigma, equal_spacing`` of the GT
        instance / RP. Empty when every count is exact.
    """
    ds = _load(dataset_dir, {"pred": pred_dir}, images)
    preds = ds.preds["pred"]
    rows: list[dict[str, Any]] = []
    for f, gts in ds.gt.items():
        res = preds[f]
        if res is None:
            continue
        _, counted = _score_counting(res, gts, h, min_rp_precision)
        truth = ds.truth.get(f, {})
        tpat = truth.get("patterns") or []
        for g, i in sorted(counted.items()):
            gt_boxes = np.asarray(gts[g].boxes, float).reshape(-1, 4)
            pat = res.patterns[i]
            if pat.count == len(gt_boxes):
                continue
            det = np.array([ins.bbox for ins in pat.instances], float).reshape(-1, 4)
            pairs = match_boxes(det, gt_boxes, h)
            hit_g, hit_d = {b for _, b in pairs}, {a for a, _ in pairs}
            # the truth record of this GT RP: same category name (synthetic: unique)
            tp = [q for q in tpat if isinstance(q, dict) and q.get("category") == gts[g].category]
            tp0 = tp[0] if len(tp) == 1 else {}
            base = {"image": f, "gt_rp": int(g), "pattern": int(i),
                    "det_count": int(pat.count), "gt_count": int(len(gt_boxes))}
            for j, b in enumerate(gt_boxes):
                r = dict(base, kind="matched" if j in hit_g else "missed",
                         x=b[0], y=b[1], w=b[2], h=b[3], source=None)
                t = truth_instance_at(tp0.get("instances") or [], b)
                if t is not None:
                    r.update(row=t.get("row"), col=t.get("col"),
                             occluded_fraction=t.get("occluded_fraction"))
                if truth:
                    r.update(blur_sigma=truth.get("blur_sigma"),
                             equal_spacing=tp0.get("equal_spacing"))
                rows.append(r)
            for a, ins in enumerate(pat.instances):
                if a not in hit_d:
                    b = det[a]
                    rows.append(dict(base, kind="extra", x=b[0], y=b[1], w=b[2], h=b[3],
                                     source=ins.source))
    cols = ["image", "gt_rp", "pattern", "det_count", "gt_count", "kind", "x", "y", "w",
            "h", "source", "row", "col", "occluded_fraction", "blur_sigma", "equal_spacing"]
    return pd.DataFrame(rows, columns=cols)


BREAKDOWN_COLUMNS = ("n_det", "assigned", "other_rp", "duplicate", "background", "n_rps",
                     "background_rps", "background_rp_instances")
"""The counts of :func:`detection_breakdown`, in order."""


def _gt_cover(det_rps: Sequence[Sequence[Sequence[float]]],
              gt_boxes: Sequence[Sequence[float]] | np.ndarray, h: float
              ) -> tuple[np.ndarray, set[int]]:
    """Which GT boxes one image's detections lie on, and which detections the one-to-one
    matching over all RPs takes.

    Returns ``(on, matched)``: ``on`` is (N, M) bool, detection ``i`` (all RPs' instances
    in order) covers GT box ``j`` with IOD > ``h``; ``matched`` the indices ``i`` that
    :func:`rescu.evaluation.metrics.match_boxes` pairs (the *any RP* numerator: its size
    is :attr:`rescu.evaluation.metrics.ImageScores.n_matched_any`). A detection lying on
    a GT box but not matched is a *duplicate*.
    """
    det = np.asarray([b for rp in det_rps for b in rp], float).reshape(-1, 4)
    gt = np.asarray(gt_boxes, float).reshape(-1, 4)
    if not len(det) or not len(gt):
        return np.zeros((len(det), len(gt)), bool), set()
    return iod_matrix(det, gt) > h, {i for i, _ in match_boxes(det, gt, h)}


def detection_breakdown(det_rps: Sequence[Sequence[Sequence[float]]],
                        gt_rps: Sequence[Sequence[Sequence[float]]], h: float = IOD_H,
                        min_rp_precision: float = MIN_RP_PRECISION) -> dict[str, int]:
    """Where one image's detected instances go under the paper's instance metric.

    Every detected instance falls in exactly one of

    * ``assigned``: credited by the paper's metric (matched, IOD > ``h`` one-to-one, to an
      instance of the GT RP its RP is assigned to; :func:`score_image`);
    * ``other_rp``: not credited, but matched one-to-one to a GT instance when matching
      runs across all RPs (the *any RP* figure minus the paper's: an instance on an
      object of another GT RP, or its RP assigned elsewhere);
    * ``duplicate``: on some GT box (IOD > ``h``) that another detection already took;
    * ``background``: on no GT box at all (IOD <= ``h`` with every one).

    ``n_rps`` counts the detected RPs, ``background_rps`` those with every instance on
    background and ``background_rp_instances`` their instances.

    >>> gt = [[(0, 0, 10, 10), (20, 0, 10, 10)]]
    >>> detection_breakdown([[(1, 1, 8, 8), (21, 1, 8, 8), (22, 2, 6, 6)],
    ...                      [(50, 50, 5, 5), (60, 50, 5, 5)]], gt)["background"]
    2
    """
    on, matched = _gt_cover(det_rps, [b for rp in gt_rps for b in rp], h)
    n = len(on)
    assigned = score_image(det_rps, gt_rps, h, min_rp_precision).n_matched
    on_gt = on.any(axis=1)
    background = int(n - on_gt.sum())
    bg_rps = bg_inst = 0
    start = 0
    for rp in det_rps:
        k = len(rp)
        if k and not on_gt[start:start + k].any():
            bg_rps, bg_inst = bg_rps + 1, bg_inst + k
        start += k
    return {"n_det": n, "assigned": assigned, "other_rp": len(matched) - assigned,
            "duplicate": int(on_gt.sum()) - len(matched), "background": background,
            "n_rps": len(det_rps), "background_rps": bg_rps,
            "background_rp_instances": bg_inst}


def precision_breakdown(dataset_dir: str | Path, pred_dir: str | Path, h: float = IOD_H,
                        min_rp_precision: float = MIN_RP_PRECISION) -> pd.DataFrame:
    """:func:`detection_breakdown` of every image of a dataset with a prediction.

    Returns
    -------
    DataFrame
        ``image`` and the :data:`BREAKDOWN_COLUMNS`, one row per image.
    """
    rows = [{"image": f, **detection_breakdown(det, [g.boxes for g in gts], h,
                                               min_rp_precision)}
            for f, gts, det in _image_detections(dataset_dir, pred_dir)]
    return pd.DataFrame(rows, columns=["image", *BREAKDOWN_COLUMNS])


def _image_detections(dataset_dir: str | Path, pred_dir: str | Path
                      ) -> list[tuple[str, list[GroundTruthRP], list[list[Any]]]]:
    """``(image, GT RPs, detected RPs' instance boxes)`` of every image of a dataset that
    has a prediction in ``pred_dir``."""
    ds = _load(dataset_dir, {"pred": pred_dir}, None)
    return [(f, gts, [[ins.bbox for ins in p.instances] for p in res.patterns])
            for f, gts in ds.gt.items() if (res := ds.preds["pred"][f]) is not None]


def duplicate_categories(det_rps: Sequence[Sequence[Sequence[float]]],
                         gt_rps: Sequence[GroundTruthRP], h: float = IOD_H
                         ) -> dict[str, dict[str, int]]:
    """On which GT categories one image's detections lie, and where its duplicates are.

    A detection lies on the smallest GT box it covers (IOD > ``h``). It is a
    *duplicate* when it lies on a GT box but the one-to-one matching over all RPs (the
    *any RP* figure, :func:`rescu.evaluation.metrics.match_boxes`) left it unmatched:
    the ``duplicate`` class of :func:`detection_breakdown`.

    Returns
    -------
    ``{category: {"gt": GT boxes, "on": detections lying on them, "duplicate": those of
    them that are duplicates}}``, one entry per category of ``gt_rps``; GT RPs without a
    category count as ``""``.

    >>> from rescu.io import GroundTruthRP
    >>> gt = [GroundTruthRP("window", [(0, 0, 10, 10), (20, 0, 10, 10)], {})]
    >>> duplicate_categories([[(1, 1, 4, 8), (5, 1, 4, 8), (21, 1, 8, 8)]], gt)
    {'window': {'gt': 2, 'on': 3, 'duplicate': 1}}
    """
    cats = [str(g.category or "") for g in gt_rps for _ in g.boxes]    # per GT box
    out = {c: {"gt": cats.count(c), "on": 0, "duplicate": 0} for c in cats}
    gt = np.asarray([b for g in gt_rps for b in g.boxes], float).reshape(-1, 4)
    on, matched = _gt_cover(det_rps, gt, h)
    area = gt[:, 2] * gt[:, 3]
    for i in np.nonzero(on.any(1))[0]:
        j = np.nonzero(on[i])[0]
        c = cats[int(j[np.argmin(area[j])])]
        out[c]["on"] += 1
        out[c]["duplicate"] += int(i not in matched)
    return out


def category_breakdown(dataset_dir: str | Path, pred_dir: str | Path, h: float = IOD_H
                       ) -> pd.DataFrame:
    """:func:`duplicate_categories` summed over every image of a dataset with a
    prediction: one row per GT category (``category``, ``gt``, ``on``, ``duplicate``),
    most duplicates first."""
    tot: dict[str, dict[str, int]] = {}
    for _, gts, det in _image_detections(dataset_dir, pred_dir):
        for c, v in duplicate_categories(det, gts, h).items():
            t = tot.setdefault(c, dict.fromkeys(v, 0))
            for k in v:
                t[k] += v[k]
    df = pd.DataFrame([{"category": c, **v} for c, v in tot.items()],
                      columns=["category", "gt", "on", "duplicate"])
    return df.sort_values(["duplicate", "category"], ascending=[False, True],
                          kind="stable").reset_index(drop=True)


def merge_pair_rows(stage1: ImageResult, rp_index: Sequence[int], inst_feats: np.ndarray,
                    inst_rp: np.ndarray, gt_rps: Sequence[GroundTruthRP],
                    params: MergeParams | None = None, h: float = IOD_H,
                    min_rp_precision: float = MIN_RP_PRECISION
                    ) -> list[dict[str, Any]]:
    """Is RESCU-II's split-RP merge right on one image? The merge evidence of every pair
    of the RPs stage II works on, labelled by the ground truth.

    Parameters
    ----------
    stage1 : ImageResult
        The RESCU-I result: its instance boxes are assigned to the GT; the evidence
        takes them before the box refinement (each RP's ``extra["box_transform"]``
        undone), as the pipeline's merge does.
    rp_index : sequence of int
        Positions in ``stage1.patterns`` of the RPs stage II works on (``rp_index`` of
        the stage-II features file).
    inst_feats : (N, D) float
        Backbone feature of every stage-I instance (``merge_instance_features`` where
        the features file has it, else ``instance_features``: what the merge compares).
    inst_rp : (N,) int
        Position in ``rp_index`` of each instance's RP (``instance_rp``).
    gt_rps : sequence of GroundTruthRP
        The image's ground truth (may be empty: every label is then -1).
    params : MergeParams, optional
        The merge's tunables; default ``MergeParams()``.
    h, min_rp_precision : float
        The RP-level matching of :func:`rescu.evaluation.metrics.score_image` that assigns each RP
        to a GT RP (IOD threshold; smallest precision of an accepted RP).

    Returns
    -------
    list of dict
        One per pair with evidence (both RPs have two or more instances with features):
        ``a, b`` (pattern positions), ``gt_a, gt_b`` (the assigned GT RP index, -1 for
        none), ``same`` (both assigned to the same GT RP), ``objects`` (both RPs are
        whole objects: the merge's line test for objects), and the ``merge, ratio, s_ab,
        s_aa, s_bb, size_ratio, conflicts, line_residual`` of
        :func:`rescu.extension.merge.pair_evidence`. The pipeline's merge
        also sees the stage-II instances in the conflict and line tests, so its decision
        can differ in those (never in the appearance test).
    """
    from rescu.discovery.sources import is_whole_object
    from rescu.extension.merge import MergeParams, pair_evidence

    params = params if params is not None else MergeParams()
    f = np.asarray(inst_feats, np.float64)
    irp = np.asarray(inst_rp).reshape(-1)
    if f.ndim != 2 or len(f) != len(irp):
        raise ValueError(f"inst_feats must be (N, D) with N = len(inst_rp) = {len(irp)}, "
                         f"got {f.shape}")
    from rescu.discovery.edge_extent import unrefined_boxes

    boxes = [np.array([i.bbox for i in stage1.patterns[pi].instances], float).reshape(-1, 4)
             for pi in rp_index]
    tested = [unrefined_boxes(stage1.patterns[pi]) for pi in rp_index]   # as the merge
    assigned = score_image(boxes, [g.boxes for g in gt_rps], h, min_rp_precision).rp_assignment
    label = [-1 if g is None else int(g) for g in assigned]
    rows = []
    for x in range(len(rp_index)):
        for y in range(x + 1, len(rp_index)):
            objects = (is_whole_object(stage1.patterns[rp_index[x]])
                       and is_whole_object(stage1.patterns[rp_index[y]]))
            ev = pair_evidence(f[irp == x], f[irp == y], tested[x], tested[y], params,
                               objects=objects)
            if np.isnan(ev["ratio"]):       # an RP with fewer than 2 featured instances
                continue
            rows.append({"a": int(rp_index[x]), "b": int(rp_index[y]), "gt_a": label[x],
                         "gt_b": label[y], "same": bool(label[x] >= 0 and label[x] == label[y]),
                         "objects": objects,
                         **{k: ev[k] for k in ("merge", "ratio", "s_ab", "s_aa", "s_bb",
                                               "size_ratio", "conflicts", "line_residual")}})
    return rows


def rp_precisions(det_rps: Sequence[Sequence[Sequence[float]]],
                  gt_rps: Sequence[Sequence[Sequence[float]]], h: float = IOD_H
                  ) -> np.ndarray:
    """Each detected RP's instance precision against its best GT RP, on its own.

    The share of the RP's instances matched one-to-one (IOD > ``h``) to instances of the
    GT RP that gives the highest share (:func:`score_image` of that RP alone). An RP is
    acceptable to the paper's RP-level metric at 0.5 or more (with two matches).

    Parameters
    ----------
    det_rps : list of lists of ``[x, y, w, h]``, pixels
    gt_rps : list of lists of ``[x, y, w, h]``, pixels

    Returns
    -------
    (len(det_rps),) float in [0, 1]; 0 for an RP without instances or an image without
    GT RPs

    >>> gt = [[(0, 0, 10, 10), (20, 0, 10, 10)]]
    >>> rp_precisions([[(1, 1, 8, 8), (50, 50, 5, 5)], [(50, 50, 5, 5)]], gt).tolist()
    [0.5, 0.0]
    """
    return np.array([score_image([rp], gt_rps, h).instance_precision if len(rp) else 0.0
                     for rp in det_rps], float).reshape(-1)
