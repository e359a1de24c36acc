"""Counting over a dataset: the counts of matched RPs and the counting table.

A detected RP counts a ground-truth RP when it is accepted for it by the RP-level
matching of :func:`rescu.evaluation.metrics.score_image`; of several accepted for one
GT RP, the one with the most instances counts it
(:func:`rescu.scene.counting.counting_patterns`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from ..io import GroundTruthRP
from ..scene.counting import counting_patterns
from ..types import ImageResult
from .core import _boxes, _dominant_index, _image_info, _load, evaluate_rp_dataset
from .metrics import IOD_H, METRICS, MIN_RP_PRECISION, ImageScores, score_image


def _score_counting(res: ImageResult | None, gts: list[GroundTruthRP], h: float,
                    min_rp_precision: float) -> tuple[ImageScores, dict[int, int]]:
    """An image's scores and ``{GT RP index: detected RP index that counts it}``
    (:func:`rescu.scene.counting.counting_patterns`); no prediction counts nothing."""
    s = score_image(_boxes(res), [g.boxes for g in gts], h, min_rp_precision)
    det_counts = [p.count for p in res.patterns] if res is not None else []
    return s, counting_patterns(det_counts, s.rp_assignment)


def count_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Counts of matched RPs: one row per detected RP accepted for a GT RP.

    Returns
    -------
    DataFrame
        ``dataset, image, method, pattern, gt_rp, det_count, gt_count, abs_error,
        exact, dominant, counted`` (``dominant``: the prediction's dominant RP;
        ``counted``: this row is the one that counts the GT RP — of the detected RPs
        accepted for one GT RP, the one with the most instances, ties the first, as
        :func:`rescu.scene.counting.counting_patterns` defines), plus one row with ``gt_rp = -1``
        (and NaN counts) for each image whose dominant RP is not accepted, so that the
        dominant-RP rates can count them.
    """
    ds = _load(dataset_dir, pred_dirs, images)
    rows = []
    for method, preds in ds.preds.items():
        for f, gts in ds.gt.items():
            res = preds[f]
            s, counting = _score_counting(res, gts, h, min_rp_precision)
            dom = _dominant_index(res)
            counted = set(counting.values())
            for i, g in enumerate(s.rp_assignment):
                if g is None and i != dom:
                    continue
                det_n = res.patterns[i].count if res is not None else 0
                gt_n = len(gts[g].boxes) if g is not None else float("nan")
                rows.append({"dataset": ds.name, "image": f, "method": method,
                             **_image_info(ds, f), "pattern": i,
                             "gt_rp": -1 if g is None else int(g), "det_count": det_n,
                             "gt_count": gt_n,
                             "abs_error": abs(det_n - gt_n) if g is not None else float("nan"),
                             "exact": bool(g is not None and det_n == gt_n),
                             "dominant": i == dom, "counted": i in counted})
    return pd.DataFrame(rows, columns=["dataset", "image", "method", "subset", "hard",
                                       "pattern", "gt_rp", "det_count", "gt_count",
                                       "abs_error", "exact", "dominant", "counted"])


def counting_table(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                   h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Counting table per dataset and method (as the paper's grocery table).

    Columns: ``n_matched`` (GT RPs that some detected RP is accepted for), ``count_mae``
    and ``exact_rate`` over them, each GT RP counted by its accepted detected RP with the
    most instances (:func:`rescu.scene.counting.count_pairs`); ``n_matched_rps``,
    ``count_mae_all_rps`` and ``exact_rate_all_rps`` over every accepted detected RP (a
    GT RP split into two detected RPs, or a part of the object found as its own RP,
    gives two rows here, both usually short);
    ``n_dominant`` (images with a prediction that has a dominant RP),
    ``dominant_matched_rate``, ``dominant_count_mae`` and ``dominant_exact_rate`` (the
    latter two over matched dominant RPs); and the mean RP-level / instance-level
    precision and recall over images (:func:`evaluate_rp_dataset`), plus the pooled
    (micro) instance precision/recall.
    """
    cf = count_frame(dataset_dir, pred_dirs, h, min_rp_precision, images=images)
    sf = evaluate_rp_dataset(dataset_dir, pred_dirs, h, min_rp_precision, images=images)
    pooled = _pooled_instance_pr(sf)
    rows = []
    for (dsn, method), g in sf.groupby(["dataset", "method"], sort=False):
        c = cf[(cf["dataset"] == dsn) & (cf["method"] == method)]
        matched_all = c[c["gt_rp"] >= 0]
        matched = matched_all[matched_all["counted"].astype(bool)]
        dom = c[c["dominant"].astype(bool)]
        dom_m = dom[dom["gt_rp"] >= 0]
        r: dict[str, Any] = {"dataset": dsn, "method": method,
                             "n_images": int(g["image"].nunique()),
                             "n_matched": int(len(matched)),
                             "count_mae": _mean(matched["abs_error"]),
                             "exact_rate": _mean(matched["exact"]),
                             "n_matched_rps": int(len(matched_all)),
                             "count_mae_all_rps": _mean(matched_all["abs_error"]),
                             "exact_rate_all_rps": _mean(matched_all["exact"]),
                             "n_dominant": int(len(dom)),
                             "dominant_matched_rate": (len(dom_m) / len(dom) if len(dom)
                                                       else float("nan")),
                             "dominant_count_mae": _mean(dom_m["abs_error"]),
                             "dominant_exact_rate": _mean(dom_m["exact"])}
        for met in METRICS:
            r[met] = _mean(g[met])
        r.update(pooled[method])
        rows.append(r)
    return pd.DataFrame(rows)


def _mean(s: pd.Series) -> float:
    v = s.to_numpy(float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


def _pooled_instance_pr(sf: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Pooled (micro) instance precision / recall per method of a per-image frame."""
    out = {}
    for method, g in sf.groupby("method", sort=False):
        matched = float(g["n_matched"].sum())
        nd, ng = int(g["n_det_instances"].sum()), int(g["n_gt_instances"].sum())
        out[str(method)] = {"instance_precision_pooled": matched / nd if nd else float("nan"),
                            "instance_recall_pooled": matched / ng if ng else float("nan")}
    return out
