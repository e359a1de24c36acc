"""Evaluation over whole datasets: loading, RP tables, significance, writers (its
parameters, :class:`EvaluationParams`, live in :mod:`rescu.params`).

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
over the images where both values are defined (finite), all through
:func:`paired_wilcoxon`. When all paired differences are zero the p-value is 1. In
Markdown the best mean is bold and a method whose difference to the best is *not*
significant (p >= alpha) is in italics, as in the paper.

The other tables build on this module: :mod:`rescu.evaluation.count_table`,
:mod:`rescu.evaluation.vpd` (vanishing points), :mod:`rescu.evaluation.ts`
(translation symmetry), :mod:`rescu.evaluation.failures`; their figures are in
:mod:`rescu.evaluation.plots`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..io import GroundTruthRP, InputError, atomic_path, load_coco_rps, read_json, read_result
from ..params import EvaluationParams
from ..types import ImageResult
from .metrics import IOD_H, METRICS, MIN_RP_PRECISION, score_image


ABLATION_ROWS = ("none", "P_d", "P_s", "P_theta", "P_d+P_s", "P_d+P_theta",
                 "P_s+P_theta", "all")
"""Rows of the stage-I ablation table: which parameters are adaptive."""

METRIC_LABELS = {"instance_precision": "Instance P", "instance_recall": "Instance R",
                 "rp_precision": "RP P", "rp_recall": "RP R",
                 "instance_precision_any": "Instance P (any RP)",
                 "instance_recall_any": "Instance R (any RP)"}

RP_TABLE_NOTE = (
    "Instance P / R are the paper's: a detected RP's instances are matched one-to-one only "
    "to the instances of the ground-truth RP assigned to it (its highest instance "
    "precision), each ground-truth instance counted once. The *any RP* columns match all "
    "detected instances against all ground-truth instances of the image, whichever RP they "
    "belong to (the figure of earlier versions of these tables); see "
    "`rescu/evaluation/metrics.py`.")


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
                        h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION,
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
        ``n_det_instances, n_gt_instances, n_det_rps, n_gt_rps``, ``n_matched`` and
        ``n_matched_any`` (the instance figures' numerators: credited instances, and
        instances matched across RPs), ``gt_categories``.

    Examples
    --------
    A one-image dataset (a tiny synthetic photo and its COCO boxes) scored against
    stage I's result:

    >>> import json, tempfile, cv2
    >>> from pathlib import Path
    >>> from rescu import discover, example_image
    >>> img, truth = example_image()
    >>> data = Path(tempfile.mkdtemp())
    >>> (data / "images").mkdir()
    >>> cv2.imwrite(str(data / "images" / "row.png"), img[:, :, ::-1])
    True
    >>> coco = {"images": [{"id": 1, "file_name": "images/row.png"}],
    ...         "categories": [{"id": 1, "name": "square"}],
    ...         "annotations": [{"id": i, "image_id": 1, "category_id": 1, "bbox": list(b)}
    ...                         for i, b in enumerate(truth)]}
    >>> _ = (data / "annotations.json").write_text(json.dumps(coco))
    >>> _ = discover(data / "images" / "row.png", data / "rescu-i", method="rescu-i")
    >>> scores = evaluate_rp_dataset(data, {"rescu-i": data / "rescu-i"})
    >>> row = scores.iloc[0]
    >>> row.method, float(row.instance_recall), float(row.rp_recall), int(row.n_gt_instances)
    ('rescu-i', 1.0, 1.0, 5)
    """
    if not 0.0 < h < 1.0:
        raise ValueError(f"h must be in (0, 1), got {h}")
    return _score_frame(_load(dataset_dir, pred_dirs, images), h, min_rp_precision)


def paired_wilcoxon(a: Sequence[float], b: Sequence[float]) -> tuple[float, int]:
    """Two-sided Wilcoxon signed-rank p-value of paired samples and the pair count.

    Pairs with a non-finite value are left out. Returns ``(nan, n)`` with no pair and
    ``(1.0, n)`` when every difference is zero. The p-value is that of
    ``scipy.stats.wilcoxon(a, b)``; for at most 13 pairs with ties or zero differences,
    where SciPy runs its exhaustive sign-flip permutation test one sign pattern at a time
    (about a second per test), it is computed by :func:`_sign_flip_pvalue` at once.

    >>> paired_wilcoxon([0.5, 0.7, 0.9, 0.2], [0.5, 0.6, 0.8, 0.1])
    (0.25, 4)
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
    p = _sign_flip_pvalue(d)
    return (float(wilcoxon(a[ok], b[ok]).pvalue) if p is None else p), n


def _sign_flip_pvalue(d: np.ndarray) -> float | None:
    """The two-sided p-value ``scipy.stats.wilcoxon`` gives the differences ``d`` (n,)
    when it runs its exhaustive permutation test (``method="auto"``, n <= 13, ties among
    the |d| or zeros in d); None otherwise.

    The statistic is the sum of the ranks (average ranks of |d|, zeros left out, as
    ``zero_method="wilcox"``) of the positive differences; its null distribution, every
    pattern of signs of the non-zero differences, is enumerated at once (flipping a zero
    changes nothing, so SciPy's 2^n patterns hold each of these 2^m equally often and
    the shares are the same). The p-value is twice the smaller tail share, counting the
    null values within SciPy's relative tolerance (100 machine epsilons) of the observed
    one, at most 1.
    """
    from scipy.stats import rankdata

    nonzero = d[d != 0]
    size = np.abs(nonzero)
    if len(d) > 13 or (len(nonzero) == len(d) and len(np.unique(size)) == len(size)):
        return None
    rank = rankdata(size)
    observed = float(rank[nonzero > 0].sum())
    m = len(nonzero)
    null = ((np.arange(2 ** m)[:, None] >> np.arange(m)) & 1).astype(float) @ rank
    tol = abs(np.finfo(float).eps * 100 * observed)
    less = np.count_nonzero(null <= observed + tol) / float(2 ** m)
    greater = np.count_nonzero(null >= observed - tol) / float(2 ** m)
    return float(np.clip(min(less, greater) * 2, 0.0, 1.0))


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
                     row_label: str = "method", title: str | None = None,
                     note: str = "") -> str:
    """Markdown tables of a :func:`summary_table`: one per dataset and subset.

    The best mean is **bold**; a method not significantly different from the best
    (Wilcoxon p >= ``alpha``) is in *italics*. ``note`` is appended below the legend.
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
    if note:
        lines += ["", note]
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
    """Write a table as TSV (full float precision, ``NaN`` for undefined), atomically.
    A table without columns (no ground truth for it) is an empty file."""
    with atomic_path(path) as tmp:
        if len(df.columns):
            df.to_csv(tmp, sep="\t", index=False, na_rep="NaN", float_format="%.10g")
        else:
            tmp.write_bytes(b"")


def read_tsv(path: str | Path) -> pd.DataFrame:
    """Read a table written by :func:`write_tsv` (an empty file: an empty table)."""
    if Path(path).stat().st_size == 0:
        return pd.DataFrame()
    return pd.read_csv(path, sep="\t", na_values=["NaN"], keep_default_na=False)


def write_markdown(text: str, path: str | Path) -> None:
    """Write Markdown text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


# ----------------------------------------------------------------------------- curves
def metric_curves(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                  hs: Sequence[float] = EvaluationParams.h_curve,
                  min_rp_precision: float = MIN_RP_PRECISION,
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


# ----------------------------------------------------------------------------- ablation
def ablation_table(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                   h: float = IOD_H, min_rp_precision: float = MIN_RP_PRECISION,
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
