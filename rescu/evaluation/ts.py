"""Translation symmetry over a dataset: cross ratios per pattern and the SR_ts sweep.

A pattern shows TS at tolerance ``t`` when ``|cross_ratio - 4/3| <= t``. SR_ts(t) is the
share of images with at least one such pattern (``which="any"``) or with a dominant
pattern that is one (``"dominant"``). On synthetic data the true-positive rate is
measured over the GT RPs with equal 3D spacing and the false-positive rate over the
others, in both cases over the GT RPs that some predicted pattern with a finite cross
ratio is assigned to (:func:`rescu.evaluation.metrics.score_image` ``rp_assignment``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import pandas as pd

from ..io import GroundTruthRP
from ..params import TS_WHICH
from ..scene.symmetry import CR_EQUAL_SPACING
from .core import EvaluationParams, _boxes, _Dataset, _dominant_index, _image_info, _load
from .metrics import IOD_H, MIN_RP_PRECISION, score_image


def _truth_gt_flags(ds: _Dataset, f: str, gts: list[GroundTruthRP]) -> list[bool | None]:
    """``equal_spacing`` of each GT RP from truth.json (matched by category), or None."""
    t = ds.truth.get(f)
    if not t:
        return [None] * len(gts)
    by_cat: dict[str, Any] = {}
    for p in t.get("patterns", []):
        for key in (p.get("category"), p.get("category_id")):
            if key is not None:
                by_cat[str(key)] = p.get("equal_spacing")
    return [None if by_cat.get(g.category) is None else bool(by_cat[g.category])
            for g in gts]


def ts_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
             h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Cross ratios of the predicted patterns, per image x method x pattern.

    Returns
    -------
    DataFrame
        ``dataset, image, method, subset, hard, pattern (-1: image without a
        pattern), dominant, cross_ratio (NaN: no TS result), ts_detected (the method's
        own flag), gt_rp (-1: not accepted), gt_equal_spacing (truth.json; None when
        unknown)``.
    """
    ds = _load(dataset_dir, pred_dirs, images)
    rows = []
    for method, preds in ds.preds.items():
        for f, gts in ds.gt.items():
            res = preds[f]
            info = {"dataset": ds.name, "image": f, "method": method, **_image_info(ds, f)}
            if res is None or not res.patterns:
                rows.append({**info, "pattern": -1, "dominant": False,
                             "cross_ratio": float("nan"), "ts_detected": False,
                             "gt_rp": -1, "gt_equal_spacing": None})
                continue
            s = score_image(_boxes(res), [g.boxes for g in gts], h, min_rp_precision)
            flags = _truth_gt_flags(ds, f, gts)
            dom = _dominant_index(res)
            for i, p in enumerate(res.patterns):
                ts = p.translation_symmetry
                g = s.rp_assignment[i]
                rows.append({**info, "pattern": i, "dominant": i == dom,
                             "cross_ratio": float(ts.cross_ratio) if ts else float("nan"),
                             "ts_detected": bool(ts.detected) if ts else False,
                             "gt_rp": -1 if g is None else int(g),
                             "gt_equal_spacing": None if g is None else flags[g]})
    return pd.DataFrame(rows)


def ts_sweep(frame: pd.DataFrame, t_values: Sequence[float] = EvaluationParams.ts_t_fine,
             which: str = "any") -> pd.DataFrame:
    """SR_ts(t) and, where truth is known, TPR / FPR, for each tolerance t.

    Returns
    -------
    DataFrame
        ``dataset, method, t, sr_ts, n_images, tpr, n_equal, fpr, n_unequal`` (NaN rates
        where undefined) plus ``sr_ts_flag`` (share of images whose method flagged TS,
        independent of t).
    """
    if which not in TS_WHICH:
        raise ValueError(f"which must be one of {TS_WHICH}, got {which!r}")
    rows = []
    for (dsn, method), g in frame.groupby(["dataset", "method"], sort=False):
        images = list(dict.fromkeys(g["image"]))
        sel = g if which == "any" else g[g["dominant"]]
        dev = (sel["cross_ratio"] - CR_EQUAL_SPACING).abs()
        flag = sel.groupby("image")["ts_detected"].any()
        known = sel[(sel["gt_rp"] >= 0) & sel["gt_equal_spacing"].notna()
                    & sel["cross_ratio"].notna()]
        for t in t_values:
            hit = sel.assign(hit=dev <= float(t)).groupby("image")["hit"].any()
            sr = float(hit.reindex(images, fill_value=False).mean()) if images else float("nan")
            r = {"dataset": dsn, "method": method, "t": float(t), "sr_ts": sr,
                 "n_images": len(images),
                 "sr_ts_flag": float(flag.reindex(images, fill_value=False).mean())
                 if images else float("nan")}
            if len(known):
                k = known.assign(hit=(known["cross_ratio"] - CR_EQUAL_SPACING).abs() <= t)
                per_gt = k.groupby(["image", "gt_rp"]).agg(
                    hit=("hit", "any"), eq=("gt_equal_spacing", "first"))
                eq = per_gt[per_gt["eq"].astype(bool)]
                ne = per_gt[~per_gt["eq"].astype(bool)]
                r.update(tpr=float(eq["hit"].mean()) if len(eq) else float("nan"),
                         n_equal=int(len(eq)),
                         fpr=float(ne["hit"].mean()) if len(ne) else float("nan"),
                         n_unequal=int(len(ne)))
            else:
                r.update(tpr=float("nan"), n_equal=0, fpr=float("nan"), n_unequal=0)
            rows.append(r)
    return pd.DataFrame(rows)
