"""Evaluation tables, curves and significance tests over whole datasets.

Builds on :mod:`rescu.evaluation.metrics` (IOD protocol documented there). Inputs:

* a dataset folder with ``annotations.json`` (COCO; GT RPs via
  :func:`rescu.io.load_coco_rps`), optionally ``truth.json`` (synthetic benchmark:
  subset ``frontal`` / ``projective``, ``hard``, per-pattern ``equal_spacing``) and
  ``vanishing_points.json``;
* per method a folder of per-image predictions ``<image stem>.json``
  (:func:`rescu.io.read_result`). A missing prediction counts as no detection and is
  flagged in the ``prediction_missing`` column.

Every table is a :class:`pandas.DataFrame`; :func:`write_tsv` (numbers, machine
readable) and :func:`write_markdown` (human, "0.93 ± 0.05") write atomically.

Significance: paired two-sided Wilcoxon signed-rank tests between methods, per metric,
over the images where both values are defined (finite). When all paired differences are
zero the p-value is 1. In Markdown the best mean is bold and a method whose difference to
the best is *not* significant (p >= alpha) is in italics, as in the paper.

Vanishing points (choices documented here): the prediction is the image-level
``vanishing_point``; it is compared with the *closest* ground-truth VP, separately for
each error (:func:`rescu.scene.vp.errors.closest_gt_error`): the point error is the pixel distance
between the dehomogenised points (:func:`rescu.scene.vp.errors.point_error`; infinite when exactly
one lies at infinity), the angle error the angle between the back-projected 3D
directions (:func:`rescu.scene.vp.errors.vector_error`; sign-free), with the true focal length and
principal point where the dataset gives them, else ``f = (w + h) / 4`` and the image
centre. A missing prediction has infinite errors (a failure at every threshold).

Translation symmetry: a pattern shows TS at tolerance ``t`` when
``|cross_ratio - 4/3| <= t``. SR_ts(t) is the share of images with at least one such
pattern (``which="any"``) or with a dominant pattern that is one (``"dominant"``). On
synthetic data the true-positive rate is measured over the GT RPs with equal 3D spacing
and the false-positive rate over the others, in both cases over the GT RPs that some
predicted pattern with a finite cross ratio is assigned to (rescu.evaluation.metrics rp_assignment).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..io import (GroundTruthRP, InputError, atomic_path, load_coco_rps, load_vanishing_points,
                  read_json, read_result)
from ..scene.counting import counting_patterns
from .metrics import METRICS, ImageScores, match_boxes, score_image
from ..types import ImageResult
from ..params import checked_mapping

if TYPE_CHECKING:     # imported where used: no table rule reads rescu/extension/merge.py
    from ..extension.merge import MergeParams

CROSS_RATIO_EQUAL = 4.0 / 3.0  # cross ratio of 4 equally spaced collinear points

ABLATION_ROWS = ("none", "P_d", "P_s", "P_theta", "P_d+P_s", "P_d+P_theta",
                 "P_s+P_theta", "all")
"""Rows of the stage-I ablation table: which parameters are adaptive."""

METRIC_LABELS = {"instance_precision": "Instance P", "instance_recall": "Instance R",
                 "rp_precision": "RP P", "rp_recall": "RP R"}


# ----------------------------------------------------------------------------- params
@dataclass(frozen=True)
class EvaluationParams:
    """Parameters of the evaluation.

    Attributes
    ----------
    iod_h : float
        IOD threshold h of an acceptable detection, (0, 1).
    min_rp_precision : float
        Precision a detected RP needs against its GT RP to be accepted, [0, 1].
    h_curve : tuple of float
        IOD thresholds of the metric-vs-h curves.
    significance_alpha : float
        Significance level of the Wilcoxon tests (italics in Markdown).
    vp_px_thresholds : tuple of float
        Point-error thresholds of the VPD success rate, pixels.
    vp_deg_thresholds : tuple of float
        Angle-error thresholds of the VPD success rate, degrees.
    ts_t_fine, ts_t_coarse : tuple of float
        Cross-ratio tolerances t of the SR_ts sweeps over (0, 0.15] and (0, 1].
    ts_which : str
        ``"any"`` pattern or the ``"dominant"`` one decides an image's TS.
    decimals : int
        Decimals in Markdown tables.
    """

    iod_h: float = 0.5
    min_rp_precision: float = 0.5
    h_curve: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    significance_alpha: float = 0.05
    vp_px_thresholds: tuple[float, ...] = (5, 10, 20, 30, 50, 75, 100)
    vp_deg_thresholds: tuple[float, ...] = (1, 2, 3, 5, 10, 15, 20)
    ts_t_fine: tuple[float, ...] = tuple(round(0.01 * k, 2) for k in range(1, 16))
    ts_t_coarse: tuple[float, ...] = tuple(round(0.05 * k, 2) for k in range(1, 21))
    ts_which: str = "any"
    decimals: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.iod_h < 1.0:
            raise ValueError(f"EvaluationParams.iod_h must be in (0, 1), got {self.iod_h}")
        if not 0.0 <= self.min_rp_precision <= 1.0:
            raise ValueError("EvaluationParams.min_rp_precision must be in [0, 1], got "
                             f"{self.min_rp_precision}")
        if not 0.0 < self.significance_alpha < 1.0:
            raise ValueError("EvaluationParams.significance_alpha must be in (0, 1), got "
                             f"{self.significance_alpha}")
        if self.ts_which not in ("any", "dominant"):
            raise ValueError("EvaluationParams.ts_which must be 'any' or 'dominant', got "
                             f"{self.ts_which!r}")
        for name in ("h_curve", "vp_px_thresholds", "vp_deg_thresholds", "ts_t_fine",
                     "ts_t_coarse"):
            v = getattr(self, name)
            if len(v) == 0 or any(not (float(x) > 0) for x in v):
                raise ValueError(f"EvaluationParams.{name} must be a non-empty list of "
                                 f"positive numbers, got {v!r}")
        if any(float(x) >= 1 for x in self.h_curve):
            raise ValueError(f"EvaluationParams.h_curve values must be in (0, 1), got "
                             f"{self.h_curve!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "EvaluationParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        d = checked_mapping(cls, d, "evaluation parameter")
        for k in ("h_curve", "vp_px_thresholds", "vp_deg_thresholds", "ts_t_fine",
                  "ts_t_coarse"):
            if k in d:
                d[k] = tuple(float(x) for x in d[k])
        return cls(**d)


# ----------------------------------------------------------------------------- loading
def load_truth(dataset_dir: str | Path) -> dict[str, dict[str, Any]]:
    """``truth.json`` of a synthetic dataset as ``{file_name: image record}``; ``{}``
    when the file is absent."""
    path = Path(dataset_dir) / "truth.json"
    if not path.exists():
        return {}
    d = read_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("images"), list):
        raise InputError(f"{path}: field 'images' missing or not a list")
    out = {}
    for i, im in enumerate(d["images"]):
        if not isinstance(im, dict) or "file_name" not in im:
            raise InputError(f"{path}: images[{i}] has no field 'file_name'")
        out[str(im["file_name"])] = im
    return out


def load_predictions(pred_dir: str | Path,
                     file_names: Iterable[str]) -> dict[str, ImageResult | None]:
    """Per-image predictions ``<pred_dir>/<image stem>.json``; None where missing."""
    pred_dir = Path(pred_dir)
    out: dict[str, ImageResult | None] = {}
    for f in file_names:
        p = pred_dir / (Path(f).stem + ".json")
        out[f] = read_result(p) if p.is_file() else None
    return out


def _check_pred_dirs(pred_dirs: Mapping[str, str | Path]) -> None:
    if not isinstance(pred_dirs, Mapping) or not pred_dirs:
        raise ValueError("pred_dirs must be a non-empty mapping {method: folder}")
    for m, d in pred_dirs.items():
        if not Path(d).is_dir():
            raise InputError(f"{d}: prediction folder of method {m!r} not found")


def _boxes(result: ImageResult | None) -> list[list[tuple[float, float, float, float]]]:
    if result is None:
        return []
    return [[i.bbox for i in p.instances] for p in result.patterns]


def _dominant_index(result: ImageResult | None) -> int | None:
    """Index of the dominant pattern (``dominant_pattern`` is a pattern id; else the
    pattern with most instances)."""
    if result is None or not result.patterns:
        return None
    d = result.dominant_pattern
    if d is not None:
        for k, p in enumerate(result.patterns):
            if p.id == d:
                return k
        if 0 <= int(d) < len(result.patterns):
            return int(d)
    return int(np.argmax([p.count for p in result.patterns]))


@dataclass
class _Dataset:
    name: str
    gt: dict[str, list[GroundTruthRP]]
    truth: dict[str, dict[str, Any]]
    preds: dict[str, dict[str, ImageResult | None]]  # method -> file -> result


def _load(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
          images: Iterable[str] | None = None) -> _Dataset:
    """Ground truth and predictions; ``images`` (file names as in the annotations,
    e.g. ``images/x.jpg``) restricts the evaluation to those images (None: all)."""
    dataset_dir = Path(dataset_dir)
    _check_pred_dirs(pred_dirs)
    gt = load_coco_rps(dataset_dir / "annotations.json")
    if images is not None:
        keep = set(images)
        gt = {f: v for f, v in gt.items() if f in keep}
    truth = load_truth(dataset_dir)
    preds = {m: load_predictions(d, gt.keys()) for m, d in pred_dirs.items()}
    return _Dataset(dataset_dir.name, gt, truth, preds)


def _image_info(ds: _Dataset, f: str) -> dict[str, Any]:
    t = ds.truth.get(f, {})
    return {"subset": t.get("subset"), "hard": t.get("hard")}


def _score_frame(ds: _Dataset, h: float, min_rp_precision: float) -> pd.DataFrame:
    rows = []
    for method, preds in ds.preds.items():
        for f, gts in ds.gt.items():
            res = preds[f]
            s = score_image(_boxes(res), [g.boxes for g in gts], h, min_rp_precision)
            rows.append({"dataset": ds.name, "image": f, "method": method,
                         **_image_info(ds, f), "prediction_missing": res is None,
                         **s.as_dict(),
                         "gt_categories": ";".join(g.category for g in gts)})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------- RP tables
def evaluate_rp_dataset(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                        h: float = 0.5, min_rp_precision: float = 0.5,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Per image x method: the 4 IOD metrics, counts and subset columns.

    Parameters
    ----------
    dataset_dir : path
        Folder with ``annotations.json`` (and ``truth.json`` for synthetic data).
    pred_dirs : {method: folder}
        Per-image prediction JSONs ``<image stem>.json``.
    h : float
        IOD threshold.
    min_rp_precision : float
        See :func:`rescu.evaluation.metrics.score_image`.

    Returns
    -------
    DataFrame
        Columns ``dataset, image, method, subset, hard, prediction_missing``, the
        metrics of :data:`rescu.evaluation.metrics.METRICS` (NaN where undefined),
        ``n_det_instances, n_gt_instances, n_det_rps, n_gt_rps, gt_categories``.
    """
    if not 0.0 < h < 1.0:
        raise ValueError(f"h must be in (0, 1), got {h}")
    return _score_frame(_load(dataset_dir, pred_dirs, images), h, min_rp_precision)


def paired_wilcoxon(a: Sequence[float], b: Sequence[float]) -> tuple[float, int]:
    """Two-sided Wilcoxon signed-rank p-value of paired samples and the pair count.

    Pairs with a non-finite value are left out. Returns ``(nan, n)`` with no pair and
    ``(1.0, n)`` when every difference is zero.
    """
    from scipy.stats import wilcoxon

    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same shape, got {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    n = int(ok.sum())
    if n == 0:
        return float("nan"), 0
    d = a[ok] - b[ok]
    if np.all(d == 0):
        return 1.0, n
    return float(wilcoxon(a[ok], b[ok]).pvalue), n


def _groups(df: pd.DataFrame) -> list[tuple[str, str, pd.DataFrame]]:
    """(dataset, subset label, rows): "all" plus each subset and hard / not hard."""
    out = []
    for ds, g in df.groupby("dataset", sort=True):
        out.append((str(ds), "all", g))
        if "subset" in g and g["subset"].notna().any():
            for s, gs in g.groupby("subset", sort=True):
                out.append((str(ds), str(s), gs))
        if "hard" in g and g["hard"].notna().any():
            hard = g["hard"].fillna(False).astype(bool)
            out.append((str(ds), "hard", g[hard]))
            out.append((str(ds), "not hard", g[~hard]))
    return out


def _paired(g: pd.DataFrame, metric: str, m1: str, m2: str,
            key: Sequence[str] = ("image",)) -> tuple[np.ndarray, np.ndarray]:
    a = g[g["method"] == m1].set_index(list(key))[metric]
    b = g[g["method"] == m2].set_index(list(key))[metric]
    a, b = a.align(b, join="inner")
    return a.to_numpy(float), b.to_numpy(float)


def summary_table(df: pd.DataFrame, metrics: Sequence[str] = METRICS,
                  higher_is_better: bool = True) -> pd.DataFrame:
    """Mean ± std per dataset, subset and method, with p-values against the best method.

    Parameters
    ----------
    df : DataFrame
        Per-image rows with ``dataset, image, method`` and the ``metrics`` columns
        (from :func:`evaluate_rp_dataset`); NaN values are left out.
    metrics : list of str
        Columns to summarise.

    Returns
    -------
    DataFrame
        One row per ``dataset, subset, method`` with ``n_images`` and, per metric,
        ``<m>_mean, <m>_std, <m>_n, <m>_best`` (bool) and ``<m>_p_vs_best`` (Wilcoxon
        p-value against the best method; NaN for the best itself).
    """
    for c in ("dataset", "image", "method", *metrics):
        if c not in df.columns:
            raise ValueError(f"df has no column {c!r}")
    rows = []
    for ds, sub, g in _groups(df):
        methods = list(dict.fromkeys(g["method"]))
        block = []
        for m in methods:
            gm = g[g["method"] == m]
            r: dict[str, Any] = {"dataset": ds, "subset": sub, "method": m,
                                 "n_images": int(gm["image"].nunique())}
            for met in metrics:
                v = gm[met].to_numpy(float)
                v = v[np.isfinite(v)]
                r[f"{met}_mean"] = float(v.mean()) if len(v) else float("nan")
                r[f"{met}_std"] = float(v.std()) if len(v) else float("nan")
                r[f"{met}_n"] = int(len(v))
            block.append(r)
        for met in metrics:
            means = np.array([r[f"{met}_mean"] for r in block], float)
            best = None
            if np.isfinite(means).any():
                vals = np.where(np.isfinite(means), means, -np.inf if higher_is_better
                                else np.inf)
                best = int(np.argmax(vals) if higher_is_better else np.argmin(vals))
            for k, r in enumerate(block):
                r[f"{met}_best"] = best is not None and k == best
                if best is None or k == best:
                    r[f"{met}_p_vs_best"] = float("nan")
                else:
                    a, b = _paired(g, met, methods[k], methods[best])
                    r[f"{met}_p_vs_best"] = paired_wilcoxon(a, b)[0]
        rows.extend(block)
    return pd.DataFrame(rows)


def significance_table(df: pd.DataFrame, metrics: Sequence[str] = METRICS
                       ) -> pd.DataFrame:
    """Paired Wilcoxon tests between every pair of methods, per dataset/subset/metric.

    Returns
    -------
    DataFrame
        ``dataset, subset, metric, method_a, method_b, n_pairs, mean_a, mean_b,
        p_value`` (means over the paired images).
    """
    rows = []
    for ds, sub, g in _groups(df):
        methods = list(dict.fromkeys(g["method"]))
        for met in metrics:
            for i, ma in enumerate(methods):
                for mb in methods[i + 1:]:
                    a, b = _paired(g, met, ma, mb)
                    p, n = paired_wilcoxon(a, b)
                    ok = np.isfinite(a) & np.isfinite(b)
                    rows.append({"dataset": ds, "subset": sub, "metric": met,
                                 "method_a": ma, "method_b": mb, "n_pairs": n,
                                 "mean_a": float(a[ok].mean()) if n else float("nan"),
                                 "mean_b": float(b[ok].mean()) if n else float("nan"),
                                 "p_value": p})
    return pd.DataFrame(rows, columns=["dataset", "subset", "metric", "method_a",
                                       "method_b", "n_pairs", "mean_a", "mean_b",
                                       "p_value"])


def format_mean_std(mean: float, std: float, decimals: int = 2) -> str:
    """``"0.93 ± 0.05"``; ``"–"`` when undefined."""
    if not np.isfinite(mean):
        return "–"
    return f"{mean:.{decimals}f} ± {std:.{decimals}f}"


def summary_markdown(summary: pd.DataFrame, metrics: Sequence[str] = METRICS,
                     alpha: float = 0.05, decimals: int = 2,
                     row_label: str = "method", title: str | None = None) -> str:
    """Markdown tables of a :func:`summary_table`: one per dataset and subset.

    The best mean is **bold**; a method not significantly different from the best
    (Wilcoxon p >= ``alpha``) is in *italics*.
    """
    lines: list[str] = []
    if title:
        lines += [f"# {title}", ""]
    for (ds, sub), g in summary.groupby(["dataset", "subset"], sort=False):
        lines += [f"## {ds} — {sub}", ""]
        head = [row_label, "images"] + [METRIC_LABELS.get(m, m) for m in metrics]
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|")
        for _, r in g.iterrows():
            cells = [str(r[row_label]), str(int(r["n_images"]))]
            for m in metrics:
                s = format_mean_std(r[f"{m}_mean"], r[f"{m}_std"], decimals)
                if s != "–":
                    if bool(r.get(f"{m}_best", False)):
                        s = f"**{s}**"
                    else:
                        p = r.get(f"{m}_p_vs_best", float("nan"))
                        if p is not None and np.isfinite(p) and p >= alpha:
                            s = f"*{s}*"
                cells.append(s)
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    lines.append(f"Mean ± std over images (undefined values left out). Bold: best; "
                 f"italics: not significantly different from the best (paired Wilcoxon "
                 f"signed-rank, p ≥ {alpha:g}).")
    return "\n".join(lines) + "\n"


def frame_markdown(df: pd.DataFrame, decimals: int = 2) -> str:
    """A plain Markdown table of any DataFrame (floats rounded to ``decimals``)."""
    cols = list(df.columns)
    out = ["| " + " | ".join(str(c) for c in cols) + " |",
           "|" + "|".join("---" for _ in cols) + "|"]
    for _, r in df.iterrows():
        cells = []
        for c in cols:
            v = r[c]
            if isinstance(v, (float, np.floating)):
                cells.append("–" if not np.isfinite(v) else f"{v:.{decimals}f}")
            else:
                cells.append(str(v))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- writers
def write_tsv(df: pd.DataFrame, path: str | Path) -> None:
    """Write a table as TSV (full float precision, ``NaN`` for undefined), atomically."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, sep="\t", index=False, na_rep="NaN", float_format="%.10g")


def read_tsv(path: str | Path) -> pd.DataFrame:
    """Read a table written by :func:`write_tsv`."""
    return pd.read_csv(path, sep="\t", na_values=["NaN"], keep_default_na=False)


def write_markdown(text: str, path: str | Path) -> None:
    """Write Markdown text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


# ----------------------------------------------------------------------------- curves
def metric_curves(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                  hs: Sequence[float] = EvaluationParams.h_curve,
                  min_rp_precision: float = 0.5,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Every metric vs the IOD threshold h, per method.

    Returns
    -------
    DataFrame
        Long format: ``dataset, method, h, metric, mean, std, n`` (mean over images
        with a defined value).
    """
    ds = _load(dataset_dir, pred_dirs, images)
    rows = []
    for h in hs:
        if not 0.0 < float(h) < 1.0:
            raise ValueError(f"every h must be in (0, 1), got {h}")
        f = _score_frame(ds, float(h), min_rp_precision)
        for method, g in f.groupby("method", sort=False):
            for met in METRICS:
                v = g[met].to_numpy(float)
                v = v[np.isfinite(v)]
                rows.append({"dataset": ds.name, "method": method, "h": round(float(h), 6),
                             "metric": met,
                             "mean": float(v.mean()) if len(v) else float("nan"),
                             "std": float(v.std()) if len(v) else float("nan"),
                             "n": int(len(v))})
    return pd.DataFrame(rows)


def _savefig(fig: Any, path: str | Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, metadata={"Software": None})


def plot_metric_curves(curves: pd.DataFrame, path: str | Path,
                       title: str | None = None) -> None:
    """PNG with one panel per metric: mean vs h, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(4 * len(METRICS), 3.4),
                             squeeze=False)
    for ax, met in zip(axes[0], METRICS):
        g = curves[curves["metric"] == met]
        for method, gm in g.groupby("method", sort=False):
            gm = gm.sort_values("h")
            ax.plot(gm["h"], gm["mean"], marker="o", ms=3, label=str(method))
        ax.set_title(METRIC_LABELS.get(met, met))
        ax.set_xlabel("IOD threshold h")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _savefig(fig, path)
    plt.close(fig)


# ----------------------------------------------------------------------------- ablation
def ablation_table(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                   h: float = 0.5, min_rp_precision: float = 0.5,
        images: Iterable[str] | None = None) -> pd.DataFrame:
    """Stage-I ablation: one row per variant x the 4 metrics.

    Parameters
    ----------
    pred_dirs : {row: folder}
        Rows named as in :data:`ABLATION_ROWS` (``"none"``, ``"P_d"``, ... ``"all"``:
        which parameters are adaptive) come first, in that order; any other rows (e.g.
        ``"all+theta-paper"``, another ``orientation_mode``) follow in the given order.

    Returns
    -------
    DataFrame
        Rows as above, columns as :func:`summary_table` for the subset "all" (p-values
        against the best row).
    """
    bad = [k for k in pred_dirs if not isinstance(k, str) or not k]
    if bad:
        raise ValueError(f"ablation row names must be non-empty strings, got {bad}")
    order = [k for k in ABLATION_ROWS if k in pred_dirs]
    order += [k for k in pred_dirs if k not in ABLATION_ROWS]
    ordered = {k: pred_dirs[k] for k in order}
    df = evaluate_rp_dataset(dataset_dir, ordered, h, min_rp_precision, images=images)
    s = summary_table(df)
    s = s[s["subset"] == "all"].rename(columns={"method": "adaptive"})
    s["adaptive"] = pd.Categorical(s["adaptive"], categories=order, ordered=True)
    return s.sort_values("adaptive").reset_index(drop=True).assign(
        adaptive=lambda x: x["adaptive"].astype(str))


# ----------------------------------------------------------------------------- counting
def _score_counting(res: ImageResult | None, gts: list[GroundTruthRP], h: float,
                    min_rp_precision: float) -> tuple[ImageScores, dict[int, int]]:
    """An image's scores and ``{GT RP index: detected RP index that counts it}``
    (:func:`rescu.scene.counting.counting_patterns`); no prediction counts nothing."""
    s = score_image(_boxes(res), [g.boxes for g in gts], h, min_rp_precision)
    det_counts = [p.count for p in res.patterns] if res is not None else []
    return s, counting_patterns(det_counts, s.rp_assignment)


def count_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                h: float = 0.5, min_rp_precision: float = 0.5,
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


def count_errors(dataset_dir: str | Path, pred_dir: str | Path, h: float = 0.5,
                 min_rp_precision: float = 0.5,
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


def merge_pair_rows(stage1: ImageResult, rp_index: Sequence[int], inst_feats: np.ndarray,
                    inst_rp: np.ndarray, gt_rps: Sequence[GroundTruthRP],
                    params: MergeParams | None = None, h: float = 0.5,
                    min_rp_precision: float = 0.5
                    ) -> list[dict[str, Any]]:
    """Is RESCU-II's split-RP merge right on one image? The merge evidence of every pair
    of the RPs stage II works on, labelled by the ground truth.

    Parameters
    ----------
    stage1 : ImageResult
        The RESCU-I result (its instance boxes are the evidence's boxes).
    rp_index : sequence of int
        Positions in ``stage1.patterns`` of the RPs stage II works on (``rp_index`` of
        the stage-II features file).
    inst_feats : (N, D) float
        Backbone feature of every stage-I instance (``instance_features``).
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
        none), ``same`` (both assigned to the same GT RP), and the ``merge, ratio, s_ab,
        s_aa, s_bb, size_ratio, conflicts, line_residual`` of
        :func:`rescu.extension.merge.pair_evidence`. The pipeline's merge
        also sees the stage-II instances in the conflict and line tests, so its decision
        can differ in those (never in the appearance test).
    """
    from ..extension.merge import MergeParams, pair_evidence

    params = params if params is not None else MergeParams()
    f = np.asarray(inst_feats, np.float64)
    irp = np.asarray(inst_rp).reshape(-1)
    if f.ndim != 2 or len(f) != len(irp):
        raise ValueError(f"inst_feats must be (N, D) with N = len(inst_rp) = {len(irp)}, "
                         f"got {f.shape}")
    boxes = [np.array([i.bbox for i in stage1.patterns[pi].instances], float).reshape(-1, 4)
             for pi in rp_index]
    assigned = score_image(boxes, [g.boxes for g in gt_rps], h, min_rp_precision).rp_assignment
    label = [-1 if g is None else int(g) for g in assigned]
    rows = []
    for x in range(len(rp_index)):
        for y in range(x + 1, len(rp_index)):
            ev = pair_evidence(f[irp == x], f[irp == y], boxes[x], boxes[y], params)
            if np.isnan(ev["ratio"]):       # an RP with fewer than 2 featured instances
                continue
            rows.append({"a": int(rp_index[x]), "b": int(rp_index[y]), "gt_a": label[x],
                         "gt_b": label[y], "same": bool(label[x] >= 0 and label[x] == label[y]),
                         **{k: ev[k] for k in ("merge", "ratio", "s_ab", "s_aa", "s_bb",
                                               "size_ratio", "conflicts", "line_residual")}})
    return rows


def counting_table(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                   h: float = 0.5, min_rp_precision: float = 0.5,
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
        # matched instances of an image = recall * GT instances (0 without GT)
        matched = float((g["instance_recall"].fillna(0.0) * g["n_gt_instances"]).round().sum())
        nd, ng = int(g["n_det_instances"].sum()), int(g["n_gt_instances"].sum())
        out[str(method)] = {"instance_precision_pooled": matched / nd if nd else float("nan"),
                            "instance_recall_pooled": matched / ng if ng else float("nan")}
    return out


# ----------------------------------------------------------------------------- VPD
def vp_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
             images: Iterable[str] | None = None) -> pd.DataFrame:
    """VP errors per image x method against ``vanishing_points.json``.

    Returns
    -------
    DataFrame
        ``dataset, image, method, vp_missing, point_error_px, angle_error_deg,
        focal_px, focal_source`` ("true" or "assumed": f = (w + h) / 4 and the image
        centre), ``n_gt_vps`` (GT VPs of the image); errors to the closest GT VP (module
        docstring), inf when missing.
        Images without a GT VP are left out.
    """
    from ..scene.vp.errors import closest_gt_error

    dataset_dir = Path(dataset_dir)
    _check_pred_dirs(pred_dirs)
    gt = load_vanishing_points(dataset_dir / "vanishing_points.json")
    if images is not None:
        keep = set(images)
        gt = {f: v for f, v in gt.items() if f in keep}
    rows = []
    for method, d in pred_dirs.items():
        preds = load_predictions(d, gt.keys())
        for f, g in gt.items():
            w, hgt = g["width"], g["height"]
            true_f = g.get("focal_px") is not None
            focal = float(g["focal_px"]) if true_f else (w + hgt) / 4.0
            pp = (g["principal_point"] if g.get("principal_point") is not None
                  else (w / 2.0, hgt / 2.0))
            if not g["vanishing_points"]:
                continue  # nothing to compare with (e.g. a frontal synthetic image)
            res = preds[f]
            vp = res.vanishing_point if res is not None else None
            if vp is None:
                pe = ae = float("inf")
            else:
                pe = closest_gt_error(vp.homogeneous, g["vanishing_points"], "point",
                                      (w, hgt), focal, pp)
                ae = closest_gt_error(vp.homogeneous, g["vanishing_points"], "vector",
                                      (w, hgt), focal, pp)
            rows.append({"dataset": dataset_dir.name, "image": f, "method": method,
                         "vp_missing": vp is None, "point_error_px": pe,
                         "angle_error_deg": ae, "focal_px": focal,
                         "focal_source": "true" if true_f else "assumed",
                         "n_gt_vps": len(g["vanishing_points"])})
    return pd.DataFrame(rows)


def vp_success_table(frame: pd.DataFrame,
                     px_thresholds: Sequence[float] = EvaluationParams.vp_px_thresholds,
                     deg_thresholds: Sequence[float] = EvaluationParams.vp_deg_thresholds
                     ) -> pd.DataFrame:
    """Success rate (share of images with error <= threshold) per method.

    Returns
    -------
    DataFrame
        Long format ``dataset, method, kind ("point_px" | "angle_deg"), threshold,
        success_rate, n_images``.
    """
    rows = []
    for (dsn, method), g in frame.groupby(["dataset", "method"], sort=False):
        for kind, col, ths in (("point_px", "point_error_px", px_thresholds),
                               ("angle_deg", "angle_error_deg", deg_thresholds)):
            e = g[col].to_numpy(float)
            for t in ths:
                rows.append({"dataset": dsn, "method": method, "kind": kind,
                             "threshold": float(t),
                             "success_rate": float(np.mean(e <= t)) if len(e) else float("nan"),
                             "n_images": int(len(e))})
    return pd.DataFrame(rows)


def vp_significance(frame: pd.DataFrame) -> pd.DataFrame:
    """Paired Wilcoxon p-values (:func:`rescu.scene.vp.errors.paired_test`: a missing VP counts as an
    error above every finite one) of the point and angle errors between method pairs."""
    from ..scene.vp.errors import paired_test

    rows = []
    for dsn, g in frame.groupby("dataset", sort=False):
        methods = list(dict.fromkeys(g["method"]))
        for col in ("point_error_px", "angle_error_deg"):
            for i, ma in enumerate(methods):
                for mb in methods[i + 1:]:
                    a, b = _paired(g, col, ma, mb)
                    rows.append({"dataset": dsn, "error": col, "method_a": ma,
                                 "method_b": mb, "n_pairs": int(len(a)),
                                 "median_a": float(np.median(a)) if len(a) else float("nan"),
                                 "median_b": float(np.median(b)) if len(b) else float("nan"),
                                 "p_value": paired_test(a, b) if len(a) else float("nan")})
    return pd.DataFrame(rows, columns=["dataset", "error", "method_a", "method_b",
                                       "n_pairs", "median_a", "median_b", "p_value"])


def vp_markdown(success: pd.DataFrame, decimals: int = 2,
                errors: pd.DataFrame | None = None) -> str:
    """Markdown: per dataset and error kind, methods x thresholds of success rate.

    With ``errors`` (:func:`vp_frame`), each dataset's first section opens with what its
    errors mean: how many images, how many GT VPs each (errors are to the closest one),
    which focal length the angle error used, and per method the median angle error and
    the number of images without a VP.
    """
    lines = []
    noted: set[str] = set()
    for (dsn, kind), g in success.groupby(["dataset", "kind"], sort=False):
        unit = "px" if kind == "point_px" else "°"
        p = g.pivot(index="method", columns="threshold", values="success_rate")
        p = p.reindex(list(dict.fromkeys(g["method"])))
        lines += [f"## {dsn} — {'point error' if kind == 'point_px' else 'angle error'}", ""]
        if errors is not None and dsn not in noted and len(errors):
            e = errors[errors["dataset"] == dsn]
            if len(e):
                noted.add(dsn)
                lines += [_vp_note(e), ""]
        head = ["method"] + [f"≤ {t:g} {unit}" for t in p.columns]
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "|".join(["---"] + ["---:"] * len(p.columns)) + "|")
        for m, r in p.iterrows():
            lines.append("| " + " | ".join([str(m)] + [f"{v:.{decimals}f}" for v in r]) + " |")
        lines.append("")
    return "\n".join(lines)


def _vp_note(e: pd.DataFrame) -> str:
    """One dataset's sentence for :func:`vp_markdown` (``e``: its rows of :func:`vp_frame`)."""
    per_image = e.drop_duplicates("image")
    n_img = len(per_image)
    k = per_image["n_gt_vps"]
    if k.min() == k.max():
        gts = f"{int(k.min())} GT VP{'s' if k.min() > 1 else ''} per image"
    else:
        gts = f"{int(k.min())}-{int(k.max())} GT VPs per image"
    closest = "; errors are to the closest GT VP" if k.max() > 1 else ""
    src = set(per_image["focal_source"])
    focal = ("the true focal length and principal point" if src == {"true"} else
             "f = (w + h) / 4 and the image centre (no focal length given)"
             if src == {"assumed"} else "the true focal length where given, else "
             "f = (w + h) / 4 and the image centre")
    per_m = []
    for m, gm in e.groupby("method", sort=False):
        med = float(np.median(gm["angle_error_deg"]))
        per_m.append(f"{m} {med:.2f}° ({int(gm['vp_missing'].sum())} without a VP)")
    return (f"{n_img} images, {gts}{closest}. Angle errors with {focal}; a missing VP "
            f"fails every threshold. Median angle error: {', '.join(per_m)}.")


def plot_vp_curves(success: pd.DataFrame, path: str | Path,
                   title: str | None = None) -> None:
    """PNG: success rate vs threshold (point and angle error), one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), squeeze=False)
    for ax, (kind, xl) in zip(axes[0], (("point_px", "point error threshold (px)"),
                                        ("angle_deg", "angle error threshold (°)"))):
        g = success[success["kind"] == kind]
        for (dsn, method), gm in g.groupby(["dataset", "method"], sort=False):
            gm = gm.sort_values("threshold")
            ax.plot(gm["threshold"], gm["success_rate"], marker="o", ms=3,
                    label=f"{method}" if success["dataset"].nunique() == 1
                    else f"{dsn}: {method}")
        ax.set_xlabel(xl)
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _savefig(fig, path)
    plt.close(fig)


# ----------------------------------------------------------------------------- TS
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
             h: float = 0.5, min_rp_precision: float = 0.5,
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
    if which not in ("any", "dominant"):
        raise ValueError(f"which must be 'any' or 'dominant', got {which!r}")
    rows = []
    for (dsn, method), g in frame.groupby(["dataset", "method"], sort=False):
        images = list(dict.fromkeys(g["image"]))
        sel = g if which == "any" else g[g["dominant"]]
        dev = (sel["cross_ratio"] - CROSS_RATIO_EQUAL).abs()
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
                k = known.assign(hit=(known["cross_ratio"] - CROSS_RATIO_EQUAL).abs() <= t)
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


# ----------------------------------------------------------------------------- failures
def collect_failures(folder: str | Path, dataset: str | None = None) -> pd.DataFrame:
    """Rows ``dataset, image, stage, message, file`` from ``*.failed.json`` files.

    Searched recursively under ``folder``; ``dataset`` is the record's own ``dataset``
    field, else the argument, else the name of the file's parent folder. An unreadable
    record becomes a row with stage ``"unreadable"``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: failures folder not found")
    rows = []
    for p in sorted(folder.rglob("*.failed.json")):
        try:
            d = json.loads(p.read_text())
            if not isinstance(d, dict):
                raise ValueError("not a JSON object")
            rows.append({"dataset": str(d.get("dataset") or dataset or p.parent.name),
                         "image": str(d.get("image", p.name[:-len(".failed.json")])),
                         "stage": str(d.get("stage", "")),
                         "message": str(d.get("message", "")), "file": str(p)})
        except (ValueError, OSError) as e:
            rows.append({"dataset": dataset or p.parent.name,
                         "image": p.name[:-len(".failed.json")], "stage": "unreadable",
                         "message": f"unreadable failure record ({e})", "file": str(p)})
    return pd.DataFrame(rows, columns=["dataset", "image", "stage", "message", "file"])


def failures_markdown(df: pd.DataFrame) -> str:
    """Markdown table of :func:`collect_failures` (messages on one line)."""
    d = df.drop(columns=["file"], errors="ignore").copy()
    d["message"] = d["message"].str.replace(r"\s+", " ", regex=True).str.replace("|", "\\|")
    if d.empty:
        return "No failures.\n"
    return frame_markdown(d)


# ----------------------------------------------------------------------------- CLI
def evaluate_predictions_cli(dataset_dir: Path, pred_dir: Path, h: float = 0.5,
                             out_dir: Path | None = None) -> int:
    """``rescu evaluate``: print the metrics of one prediction folder; return an exit code.

    Uses ``annotations.json`` (RP metrics and counting) and/or ``vanishing_points.json``
    (VP success rates) of ``dataset_dir``; a missing prediction counts as no detection.
    Writes per-image scores and tables to ``out_dir`` when given. Returns 0, or 2 when
    the dataset has no ground truth.
    """
    dataset_dir, pred_dir = Path(dataset_dir), Path(pred_dir)
    if not pred_dir.is_dir():
        raise InputError(f"{pred_dir}: prediction folder not found")
    has_rp = (dataset_dir / "annotations.json").is_file()
    has_vp = (dataset_dir / "vanishing_points.json").is_file()
    if not (has_rp or has_vp):
        raise InputError(f"{dataset_dir}: no annotations.json or vanishing_points.json")
    stems = {p.stem for p in pred_dir.glob("*.json")}
    if not stems:
        raise InputError(f"{pred_dir}: no prediction files (<image stem>.json) in folder")
    images = set()
    for name in ("annotations.json", "vanishing_points.json"):
        if (dataset_dir / name).is_file():
            d = read_json(dataset_dir / name)
            images |= {Path(str(im.get("file_name", ""))).stem
                       for im in (d.get("images") or []) if isinstance(im, dict)}
    if images and not stems & images:
        example = sorted(images)[0]
        raise InputError(f"{pred_dir}: none of its {len(stems)} JSON file(s) is named after an "
                         f"image of {dataset_dir} (expected e.g. {example}.json)")
    method = pred_dir.name or "predictions"
    if has_rp:
        scores = evaluate_rp_dataset(dataset_dir, {method: pred_dir}, h)
        summary = summary_table(scores)
        print(summary_markdown(summary, title=f"RP discovery (IOD h = {h})"))
        counting = counting_table(dataset_dir, {method: pred_dir}, h)
        print("\n## Counting\n\n" + frame_markdown(counting))
        if out_dir is not None:
            write_tsv(scores, Path(out_dir) / "rp_scores.tsv")
            write_tsv(summary, Path(out_dir) / "rp_discovery.tsv")
            write_tsv(counting, Path(out_dir) / "counting.tsv")
    if has_vp:
        frame = vp_frame(dataset_dir, {method: pred_dir})
        if len(frame):
            success = vp_success_table(frame)
            print("\n" + vp_markdown(success))
            if out_dir is not None:
                write_tsv(frame, Path(out_dir) / "vpd_errors.tsv")
                write_tsv(success, Path(out_dir) / "vpd.tsv")
    return 0
