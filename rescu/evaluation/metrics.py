"""Evaluation of recurring-pattern discovery with intersection over detection (IOD).

Protocol (the paper's, with the choices it leaves open stated here):

* IOD(det, gt) = area(det ∩ gt) / area(det). A detected instance is *acceptable* for a
  ground-truth instance when IOD > h (default h = 0.5).
* Matching is one-to-one: pairs are taken greedily in order of decreasing IOD (ties:
  larger IoU first, then lower indices), so one detection is never credited for two
  ground-truth instances nor two detections for one.
* Instance level (per image), the paper's (``instance_precision``,
  ``instance_recall``): each detected RP is *assigned* the GT RP against which its
  instance precision is highest (ties: higher recall, then the lower index; an RP that
  matches no GT instance is assigned none). A detected RP's instances are matched
  one-to-one only to the instances of the GT RP assigned to it; the detected RPs
  assigned to one GT RP are matched together, so each GT instance is counted once.
  precision = matched detections / detections; recall = matched GT instances / GT
  instances. The assignment does not need the RP to be accepted at the RP level.
* Instance level, any RP (``instance_precision_any``, ``instance_recall_any``; the
  figure these tables gave before the paper's): all detected instances of all detected
  RPs are pooled and matched against all GT instances of all GT RPs, whichever RP they
  belong to. It is never below the paper's figure; the gap measures instances credited
  to another RP's objects (e.g. an RP that mixes windows and doors).
* RP level (per image): for each detected RP, the instance-level precision against each
  ground-truth RP alone is computed; the RP is assigned the GT RP with the highest one
  (ties: higher recall). It is *accepted* when that precision is >= 0.5 and at least two
  of its instances match (an RP is a recurrence). precision = accepted RPs / detected
  RPs; recall = GT RPs covered by a one-to-one matching of detected RPs to GT RPs /
  GT RPs, where a detected RP may be matched to any GT RP it would be accepted for
  (maximum bipartite matching; so two detections of one GT RP count once, and the
  recall does not depend on the order of the RPs when a detection is acceptable for
  several GT RPs, e.g. overlapping boxes at a low h).
* A ratio with a zero denominator is undefined (NaN) and left out of the mean over
  images (e.g. precision of an image with no detection); the number of images that
  entered each mean is reported beside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..boxes import cover_matrix, iod_matrix, iou_matrix
from ..params import config_defaults
from ..types import BBox

__all__ = ["iod_matrix", "iou_matrix", "cover_matrix", "match_boxes", "ImageScores",
           "score_image", "summarise", "METRICS", "ANY_RP_METRICS", "TABLE_METRICS", "IOD_H",
           "MIN_RP_PRECISION"]   # the overlap matrices live in rescu.boxes

_E = config_defaults("evaluation")
IOD_H: float = _E["iod_h"]                        # default IOD threshold h
MIN_RP_PRECISION: float = _E["min_rp_precision"]  # default least precision of an accepted RP


def match_boxes(det: np.ndarray, gt: np.ndarray, h: float = IOD_H) -> list[tuple[int, int]]:
    """One-to-one greedy matching of detections to ground truth with IOD > h.

    Returns the matched ``(det_index, gt_index)`` pairs, in order of decreasing IOD.
    """
    det = np.asarray(det, float).reshape(-1, 4)
    gt = np.asarray(gt, float).reshape(-1, 4)
    if len(det) == 0 or len(gt) == 0:
        return []
    iod = iod_matrix(det, gt)
    iou = iou_matrix(det, gt)
    di, gi = np.nonzero(iod > h)
    order = np.lexsort((gi, di, -iou[di, gi], -iod[di, gi]))
    used_d: set[int] = set()
    used_g: set[int] = set()
    pairs = []
    for k in order:
        d, g = int(di[k]), int(gi[k])
        if d in used_d or g in used_g:
            continue
        used_d.add(d)
        used_g.add(g)
        pairs.append((d, g))
    return pairs


def _max_bipartite_matching(adj: np.ndarray) -> int:
    """Size of a maximum matching of a (D, G) bool biadjacency matrix."""
    if adj.size == 0 or not adj.any():
        return 0
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    match = maximum_bipartite_matching(csr_matrix(adj.astype(np.int8)), perm_type="column")
    return int((match >= 0).sum())


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den > 0 else float("nan")


@dataclass
class ImageScores:
    """Scores of one image (NaN where undefined)."""

    instance_precision: float
    instance_recall: float
    rp_precision: float
    rp_recall: float
    instance_precision_any: float
    instance_recall_any: float
    n_det_instances: int
    n_gt_instances: int
    n_det_rps: int
    n_gt_rps: int
    n_matched: int      # detected instances the paper's metric credits (its P and R numerator)
    n_matched_any: int  # ... when matching runs across all RPs (the *any RP* numerator)
    rp_assignment: list[int | None]  # per detected RP: assigned GT RP index or None

    def as_dict(self) -> dict[str, float | int]:
        return {k: v for k, v in self.__dict__.items() if k != "rp_assignment"}


def score_image(det_rps: Sequence[Sequence[BBox]], gt_rps: Sequence[Sequence[BBox]],
                h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION) -> ImageScores:
    """Instance- and RP-level precision and recall of one image (see module docstring).

    Parameters
    ----------
    det_rps : list of lists of ``[x, y, w, h]``
        Detected RPs, each a list of instance boxes (pixels).
    gt_rps : list of lists of ``[x, y, w, h]``
        Ground-truth RPs (pixels).
    h : float
        IOD threshold.
    min_rp_precision : float
        A detected RP is accepted when its precision against its assigned GT RP is at
        least this (and two or more of its instances match).

    >>> from rescu.data.example import example_image
    >>> _, truth = example_image(n=4)                  # one RP of 4 instances
    >>> found = [[(x + 3, y, w, h) for x, y, w, h in truth[:3]]]  # 3 of them, shifted
    >>> s = score_image(found, [truth])
    >>> s.instance_precision, s.instance_recall, s.rp_precision, s.rp_recall
    (1.0, 0.75, 1.0, 1.0)
    """
    det_all = [b for rp in det_rps for b in rp]
    gt_all = [b for rp in gt_rps for b in rp]
    n_any = len(match_boxes(np.asarray(det_all, float), np.asarray(gt_all, float), h))
    assignment: list[int | None] = []
    best_gt: list[int | None] = []          # per detected RP: GT RP of its best precision
    acceptable = np.zeros((len(det_rps), len(gt_rps)), bool)  # det RP i ok for GT RP g
    n_accepted = 0
    for i, rp in enumerate(det_rps):
        best: tuple[float, float, int] | None = None
        n_matched_best = 0
        for g, gt in enumerate(gt_rps):
            m = match_boxes(np.asarray(rp, float), np.asarray(gt, float), h)
            p = _ratio(len(m), len(rp))
            r = _ratio(len(m), len(gt))
            if np.isnan(p):
                continue
            acceptable[i, g] = p >= min_rp_precision and len(m) >= 2
            key = (p, r if not np.isnan(r) else 0.0, -g)
            if best is None or key > best:
                best, n_matched_best = key, len(m)
        best_gt.append(-best[2] if best is not None and n_matched_best > 0 else None)
        if best is not None and best[0] >= min_rp_precision and n_matched_best >= 2:
            n_accepted += 1
            assignment.append(-best[2])
        else:
            assignment.append(None)
    n_assigned = 0                          # the paper's: matches within assigned pairs
    for g, gt in enumerate(gt_rps):
        boxes = [b for rp, a in zip(det_rps, best_gt) if a == g for b in rp]
        if boxes:
            n_assigned += len(match_boxes(np.asarray(boxes, float), np.asarray(gt, float), h))
    n_recalled = _max_bipartite_matching(acceptable)
    return ImageScores(
        instance_precision=_ratio(n_assigned, len(det_all)),
        instance_recall=_ratio(n_assigned, len(gt_all)),
        rp_precision=_ratio(n_accepted, len(det_rps)),
        rp_recall=_ratio(n_recalled, len(gt_rps)),
        instance_precision_any=_ratio(n_any, len(det_all)),
        instance_recall_any=_ratio(n_any, len(gt_all)),
        n_det_instances=len(det_all), n_gt_instances=len(gt_all),
        n_det_rps=len(det_rps), n_gt_rps=len(gt_rps), n_matched=n_assigned,
        n_matched_any=n_any, rp_assignment=assignment)


METRICS = ("instance_precision", "instance_recall", "rp_precision", "rp_recall")
"""The four figures of the paper's tables."""
ANY_RP_METRICS = ("instance_precision_any", "instance_recall_any")
"""The instance figures with matching across RPs (the tables' second pair of columns)."""
TABLE_METRICS = METRICS + ANY_RP_METRICS
"""The columns of an RP discovery table."""


def summarise(scores: Sequence[ImageScores]) -> dict[str, float]:
    """Mean, std and number of images with a defined value, for each of :data:`METRICS`."""
    out: dict[str, float] = {"n_images": len(scores)}
    for m in METRICS:
        v = np.array([getattr(s, m) for s in scores], float)
        v = v[~np.isnan(v)]
        out[f"{m}_mean"] = float(v.mean()) if len(v) else float("nan")
        out[f"{m}_std"] = float(v.std()) if len(v) else float("nan")
        out[f"{m}_n"] = int(len(v))
    return out
