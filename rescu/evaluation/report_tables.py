"""The tables of the HTML report: human column names, formatted cells, the headline
figures per dataset and the compact evaluation tables (:class:`Table`).

Everything here turns the run's TSV tables (:mod:`rescu.evaluation.tables`) into what a
reader sees; :mod:`rescu.evaluation.report` lays them out on the page.
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..names import METHOD_LABELS, METHODS

# ----------------------------------------------------------------------------- names
#: Column name of the pipeline's tables -> what a reader sees as the column header.
HUMAN_NAMES: dict[str, str] = {
    "dataset": "Dataset", "subset": "Subset", "method": "Method",
    "adaptive": "Adaptive parameters", "n_images": "Images", "image": "Image",
    "instance_precision": "Instance precision", "instance_recall": "Instance recall",
    "rp_precision": "RP precision", "rp_recall": "RP recall",
    "instance_precision_pooled": "Instance precision (pooled)",
    "instance_recall_pooled": "Instance recall (pooled)",
    "n_matched": "GT patterns matched", "count_mae": "Count error (MAE)",
    "exact_rate": "Exact count rate",
    "n_matched_rps": "Detected patterns matched",
    "count_mae_all_rps": "Count error, all matched patterns",
    "exact_rate_all_rps": "Exact count rate, all matched patterns",
    "n_dominant": "Images with a dominant pattern",
    "dominant_matched_rate": "Dominant pattern matched",
    "dominant_count_mae": "Dominant count error (MAE)",
    "dominant_exact_rate": "Dominant exact count rate",
    "kind": "Error", "threshold": "Threshold", "success_rate": "Success rate",
    "error": "Error", "method_a": "Method A", "method_b": "Method B",
    "n_pairs": "Image pairs", "median_a": "Median A", "median_b": "Median B",
    "mean_a": "Mean A", "mean_b": "Mean B", "metric": "Metric", "p_value": "p-value",
    "point_error_px": "Point error (px)", "angle_error_deg": "Angle error (°)",
    "vp_missing": "Without a VP", "focal_px": "Focal length (px)",
    "focal_source": "Focal length from", "n_gt_vps": "GT VPs",
    "t": "Tolerance t", "sr_ts": "SR_ts", "sr_ts_flag": "Flagged as TS",
    "tpr": "True positive rate", "fpr": "False positive rate",
    "n_equal": "Equally spaced GT patterns", "n_unequal": "Unequally spaced GT patterns",
    "sweep": "Sweep", "stage": "Stage", "type": "Error type", "message": "Message",
    "n_patterns": "Patterns", "dominant_count": "Dominant count",
    "base": "Base caption", "enhanced": "Caption",
}
_SUFFIXES = (("_p_vs_best", ", p vs best"), ("_mean", " (mean)"), ("_std", " (std)"),
             ("_best", ", best"), ("_n", " (n)"))
_ACRONYMS = {"rp": "RP", "rps": "RPs", "vp": "VP", "vps": "VPs", "ts": "TS", "mae": "MAE",
             "tpr": "TPR", "fpr": "FPR", "px": "px", "gt": "GT", "iod": "IOD", "sr": "SR"}

#: Order of the methods in the headline tables (others follow in table order).
HEADLINE_METHODS = tuple(METHOD_LABELS[m] for m in METHODS)
RP_METRICS = ("instance_precision", "instance_recall", "rp_precision", "rp_recall")
_SHORT_METRICS = {"instance_precision": "Instance P", "instance_recall": "Instance R",
                  "rp_precision": "RP P", "rp_recall": "RP R"}


def human_name(col: str) -> str:
    """The header a reader sees for a table column (``instance_precision_mean`` ->
    ``Instance precision (mean)``); a name that is not a snake_case identifier is
    returned as it is."""
    if col in HUMAN_NAMES:
        return HUMAN_NAMES[col]
    if not re.fullmatch(r"[a-z][a-z0-9_]*", col):
        return col
    for suffix, label in _SUFFIXES:
        if col.endswith(suffix) and col[: -len(suffix)] in HUMAN_NAMES:
            return HUMAN_NAMES[col[: -len(suffix)]] + label
    words = [_ACRONYMS.get(w, w) for w in col.split("_")]
    if words[0] == "n" and len(words) > 1:
        words = ["number", "of"] + words[1:]
    text = " ".join(words)
    return text[:1].upper() + text[1:]


def md_inline(text: str) -> str:
    """HTML of one line of Markdown: escaped, with ``**bold**``, ```code``` and
    ``_italics_`` turned into tags (no Markdown syntax reaches the page)."""
    s = html.escape(text, quote=False)
    s = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", s)
    s = re.sub(r"`(.+?)`", r"<code>\1</code>", s)
    s = re.sub(r"(?<![\w])_(.+?)_(?![\w])", r"<i>\1</i>", s)
    return s.replace("**", "")


# ----------------------------------------------------------------------------- cells
def _num(v: Any, decimals: int = 2) -> str:
    """A number as a reader sees it: integers plain, floats with ``decimals``, NaN ``–``,
    infinity ``∞``."""
    if v is None or (isinstance(v, (float, np.floating)) and np.isnan(v)):
        return "–"
    if isinstance(v, (float, np.floating)) and np.isinf(v):
        return "∞" if v > 0 else "-∞"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.{decimals}f}"
    return str(v)


def mean_std(mean: Any, std: Any, decimals: int = 2) -> str:
    """``"0.98 ± 0.03"`` (``–`` when the mean is undefined)."""
    m = _num(_float(mean), decimals)
    if m == "–":
        return m
    s = _num(_float(std), decimals)
    return m if s == "–" else f"{m} ± {s}"


def _float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


#: Columns that count things (shown as integers; so is any ``n_*`` column).
COUNT_COLUMNS = {"dominant_count", "Without a VP", "Images", "With a pattern"}


def format_frame(df: pd.DataFrame, decimals: int = 2) -> pd.DataFrame:
    """Every cell as a string: counts (``n_*`` and :data:`COUNT_COLUMNS`) as integers,
    other numbers with ``decimals`` (a rate of 1 is ``1.00``), text as it is."""
    out = pd.DataFrame(index=df.index)
    for c in df.columns:
        is_count = str(c).startswith("n_") or c in COUNT_COLUMNS
        col = df[c]
        if col.dtype == bool:
            out[c] = col.map(_num)
        elif pd.api.types.is_numeric_dtype(col):
            out[c] = [_num(int(v) if is_count and np.isfinite(v) else float(v), decimals)
                      for v in col.astype(float)]
        else:
            out[c] = col.map(lambda v: _num(v, decimals) if isinstance(
                v, (int, float, np.number)) else ("–" if v is None else str(v)))
    return out


@dataclass
class Table:
    """A table as shown: formatted cells, the original column keys (headers through
    :func:`human_name`), and which cells are bold (best) or italic (not significantly
    different from the best).

    ``text`` columns are left-aligned, ``wrap`` columns may wrap (long text)."""

    cells: pd.DataFrame
    bold: pd.DataFrame | None = None
    italic: pd.DataFrame | None = None
    text: Sequence[str] = ()
    wrap: Sequence[str] = ()
    headers: Mapping[str, str] = field(default_factory=dict)
    css: str = "t"

    def to_html(self) -> str:
        cols = list(self.cells.columns)
        head = "".join(
            f'<th class="{self._cls(c)}">{html.escape(self.headers.get(c, human_name(c)))}'
            "</th>" for c in cols)
        rows = []
        for i in range(len(self.cells)):
            tds = []
            for c in cols:
                v = html.escape(str(self.cells.iloc[i][c]))
                if self.bold is not None and c in self.bold and bool(self.bold.iloc[i][c]):
                    v = f"<b>{v}</b>"
                elif self.italic is not None and c in self.italic and \
                        bool(self.italic.iloc[i][c]):
                    v = f"<i>{v}</i>"
                tds.append(f'<td class="{self._cls(c)}">{v}</td>')
            rows.append("<tr>" + "".join(tds) + "</tr>")
        return (f'<div class="tw"><table class="{self.css}"><thead><tr>{head}</tr></thead>'
                f'<tbody>{"".join(rows)}</tbody></table></div>')

    def _cls(self, c: str) -> str:
        return "wrap" if c in self.wrap else "txt" if c in self.text else "num"


def read_tsv(path: str | Path | None) -> pd.DataFrame | None:
    """The table, or None when the file does not exist; an empty file is an empty table."""
    if path is None or not Path(path).exists():
        return None
    if Path(path).stat().st_size == 0:
        return pd.DataFrame()
    return pd.read_csv(path, sep="\t")


def _method_order(methods: Iterable[str], first: Sequence[str] = HEADLINE_METHODS) -> list[str]:
    ms = list(dict.fromkeys(methods))
    return [m for m in first if m in ms] + [m for m in ms if m not in first]


def _best_mask(values: pd.Series, decimals: int, higher_is_better: bool = True) -> pd.Series:
    """True where the value equals the best one as shown (ties at ``decimals`` all bold)."""
    v = pd.to_numeric(values, errors="coerce").round(decimals)
    if not v.notna().any():
        return pd.Series(False, index=values.index)
    best = v.max() if higher_is_better else v.min()
    return (v == best).fillna(False)


def summary_cells(df: pd.DataFrame, row_cols: Sequence[str],
                  metrics: Sequence[str] = RP_METRICS, decimals: int = 2,
                  alpha: float | None = 0.05, group_cols: Sequence[str] = ("dataset", "subset"),
                  count_col: str | None = "n_images") -> Table:
    """A :func:`rescu.evaluation.core.summary_table`-style frame (``<m>_mean``, ``<m>_std``,
    ``<m>_p_vs_best`` per metric) as one cell ``mean ± std`` per metric; within each
    group (``group_cols`` present in ``df``) the best mean is bold and, with ``alpha``,
    a mean whose paired test against the best gives ``p >= alpha`` is italic."""
    groups = [c for c in group_cols if c in df.columns]
    count = [count_col] if count_col and count_col in df.columns else []
    cols = list(row_cols) + count
    cells = format_frame(df[cols], decimals)
    bold = pd.DataFrame(False, index=df.index, columns=cols)
    italic = pd.DataFrame(False, index=df.index, columns=cols)
    for m in metrics:
        if f"{m}_mean" not in df.columns:
            continue
        cells[m] = [mean_std(a, b, decimals) for a, b in
                    zip(df[f"{m}_mean"], df.get(f"{m}_std", pd.Series(np.nan, df.index)))]
        bm = (df.groupby(groups, sort=False)[f"{m}_mean"]
              .transform(lambda s: _best_mask(s, decimals)) if groups else
              _best_mask(df[f"{m}_mean"], decimals)).astype(bool)
        bold[m] = bm
        p = df.get(f"{m}_p_vs_best")
        italic[m] = (~bm & (pd.to_numeric(p, errors="coerce") >= alpha).fillna(False)) \
            if alpha is not None and p is not None else False
    order = list(row_cols) + [m for m in metrics if m in cells.columns] + count
    return Table(cells[order].reset_index(drop=True), bold[order].reset_index(drop=True),
                 italic[order].reset_index(drop=True), text=list(row_cols))


# ----------------------------------------------------------------------------- headlines
def rp_headline(rp: pd.DataFrame, dataset: str, decimals: int = 2) -> Table | None:
    """The headline of a dataset with recurring-pattern ground truth: one row per method
    (RESCU-II, RESCU-I, GRASP first), instance and RP precision / recall as mean ± std
    over all its images, the best in bold, and the number of images."""
    g = rp[rp["dataset"].astype(str) == dataset]
    if "subset" in g.columns:
        g = g[g["subset"].astype(str) == "all"]
    if g.empty:
        return None
    g = g.set_index("method").loc[_method_order(g["method"])].reset_index()
    t = summary_cells(g, ["method"], decimals=decimals, alpha=None, group_cols=())
    t.headers = dict(_SHORT_METRICS)
    t.css = "t headline"
    return t


def _nearest(values: Iterable[float], target: float) -> float | None:
    v = sorted(set(float(x) for x in values))
    return min(v, key=lambda x: (abs(x - target), x)) if v else None


def vp_headline(vpd: pd.DataFrame, dataset: str, errors: pd.DataFrame | None = None,
                px: float = 5, deg: float = 5, decimals: int = 2) -> Table | None:
    """The headline of a dataset with vanishing-point ground truth only: per method the
    share of images whose VP is within ``px`` pixels and within ``deg`` degrees (the
    nearest thresholds the run has), the median angle error, the best in bold."""
    g = vpd[vpd["dataset"].astype(str) == dataset]
    if g.empty:
        return None
    methods = list(dict.fromkeys(g["method"]))
    rows = {m: {"method": m} for m in methods}
    higher = {}
    for kind, target, unit in (("point_px", px, " px"), ("angle_deg", deg, "°")):
        gk = g[g["kind"] == kind]
        th = _nearest(gk["threshold"], target)
        if th is None:
            continue
        col = f"VP within {th:g}{unit}"
        higher[col] = True
        for m in methods:
            r = gk[(gk["method"] == m) & (gk["threshold"].astype(float) == th)]
            rows[m][col] = float(r["success_rate"].iloc[0]) if len(r) else np.nan
            rows[m]["n_images"] = int(r["n_images"].iloc[0]) if len(r) else rows[m].get(
                "n_images", 0)
    if errors is not None and len(errors):
        e = errors[errors["dataset"].astype(str) == dataset]
        if len(e):
            col = "Median angle error (°)"
            higher[col] = False
            for m in methods:
                a = e.loc[e["method"] == m, "angle_error_deg"].to_numpy(float)
                rows[m][col] = float(np.median(a)) if len(a) else np.nan
    df = pd.DataFrame(list(rows.values()))
    cols = ["method"] + list(higher) + (["n_images"] if "n_images" in df else [])
    df = df[cols]
    bold = pd.DataFrame(False, index=df.index, columns=cols)
    for c, hi in higher.items():
        bold[c] = _best_mask(df[c], decimals, hi)
    cells = format_frame(df, decimals)
    return Table(cells, bold, text=["method"], css="t headline")


def found_headline(captions: pd.DataFrame, dataset: str) -> Table | None:
    """The headline of a dataset without ground truth: what RESCU-II found (images,
    images with a pattern, patterns per image and the dominant pattern's count, medians)."""
    g = captions[captions["dataset"].astype(str) == dataset]
    if g.empty:
        return None
    n_pat = pd.to_numeric(g["n_patterns"], errors="coerce")
    dom = pd.to_numeric(g["dominant_count"], errors="coerce")
    dom = dom[dom > 0]
    row = {"Images": str(len(g)), "With a pattern": str(int((n_pat > 0).sum())),
           "Patterns per image (median)": _num(float(n_pat.median()), 1),
           "Dominant count (median)": _num(float(dom.median()), 1) if len(dom) else "–"}
    return Table(pd.DataFrame([row]), css="t headline")


# ----------------------------------------------------------------------------- compact tables
def _pick_thresholds(values: Iterable[float], k: int = 3) -> list[float]:
    """At most ``k`` of the thresholds: the smallest, the largest and the middle one."""
    v = sorted(set(float(x) for x in values))
    if len(v) <= k:
        return v
    idx = sorted(set(int(round(i * (len(v) - 1) / (k - 1))) for i in range(k)))
    return [v[i] for i in idx]


def vp_compact(vpd: pd.DataFrame, dataset: str, errors: pd.DataFrame | None = None,
               decimals: int = 2) -> Table | None:
    """Methods x a few thresholds of the VP success rate (the full sweep is the curve and
    the TSV), with the median angle error and the images without a VP. A method with a
    VP on no image of the dataset (a peer that could not run here) says "not run"
    instead of zeros."""
    g = vpd[vpd["dataset"].astype(str) == dataset]
    if g.empty:
        return None
    methods = list(dict.fromkeys(g["method"]))
    rows = {m: {"method": m} for m in methods}
    higher: dict[str, bool] = {}
    for kind, unit in (("point_px", " px"), ("angle_deg", "°")):
        gk = g[g["kind"] == kind]
        for th in _pick_thresholds(gk["threshold"]):
            col = f"≤ {th:g}{unit}"
            higher[col] = True
            for m in methods:
                r = gk[(gk["method"] == m) & (gk["threshold"].astype(float) == th)]
                rows[m][col] = float(r["success_rate"].iloc[0]) if len(r) else np.nan
                if len(r):
                    rows[m]["n_images"] = int(r["n_images"].iloc[0])
    if errors is not None and len(errors):
        e = errors[errors["dataset"].astype(str) == dataset]
        for m in methods:
            em = e[e["method"] == m]
            a = em["angle_error_deg"].to_numpy(float)  # a missing VP: inf
            rows[m]["Median angle error (°)"] = float(np.median(a)) if len(a) else np.nan
            if "vp_missing" in em:
                rows[m]["Without a VP"] = int(em["vp_missing"].astype(str).str.lower()
                                              .eq("true").sum())
        higher["Median angle error (°)"] = False
    df = pd.DataFrame(list(rows.values()))
    cols = ["method", *[c for c in higher if c in df], *[c for c in ("Without a VP",) if c in df]]
    df = df[cols]
    bold = pd.DataFrame(False, index=df.index, columns=cols)
    for c, hi in higher.items():
        if c in df:
            bold[c] = _best_mask(df[c], decimals, hi)
    cells = format_frame(df, decimals)
    for i, m in enumerate(df["method"]):
        if rows[m].get("Without a VP") is not None and rows[m]["Without a VP"] == rows[m].get(
                "n_images", -1):
            for c in cols[1:]:
                if c not in ("n_images", "Without a VP"):
                    cells.iloc[i, cols.index(c)] = "not run"
                    bold.iloc[i, cols.index(c)] = False
    return Table(cells, bold, text=["method"], headers={"n_images": "Images"})


def ts_compact(ts: pd.DataFrame, decimals: int = 2,
               t_values: Sequence[float] = (0.05, 0.10)) -> Table | None:
    """Per dataset and method: the share of images flagged as TS, SR_ts at a few
    tolerances t of the fine sweep, and TPR / FPR at the first of them (where truth is
    known). The sweep itself is the curve and the TSV."""
    if ts is None or ts.empty:
        return None
    fine = ts[ts["sweep"] == "fine"] if "sweep" in ts.columns else ts
    rows = []
    for (ds, m), g in fine.groupby(["dataset", "method"], sort=False):
        r: dict[str, Any] = {"dataset": ds, "method": m,
                             "n_images": int(g["n_images"].iloc[0])}
        if "sr_ts_flag" in g:
            r["Flagged as TS"] = float(g["sr_ts_flag"].iloc[0])
        ths = [t for t in (_nearest(g["t"], v) for v in t_values) if t is not None]
        for th in dict.fromkeys(ths):
            r[f"SR_ts at t = {th:g}"] = float(g.loc[g["t"].astype(float) == th, "sr_ts"].iloc[0])
        if ths:
            at = g[g["t"].astype(float) == ths[0]].iloc[0]
            for c, label in (("tpr", "TPR"), ("fpr", "FPR")):
                if c in g and np.isfinite(float(at[c])):
                    r[f"{label} at t = {ths[0]:g}"] = float(at[c])
        rows.append(r)
    df = pd.DataFrame(rows)
    cols = ["dataset", "method"] + [c for c in df.columns if c not in
                                    ("dataset", "method", "n_images")] + ["n_images"]
    df = df[cols]
    return Table(format_frame(df, decimals), text=["dataset", "method"],
                 headers={"n_images": "Images"})


COUNTING_COLUMNS = ("dataset", "method", "n_images", "n_matched", "count_mae", "exact_rate",
                    "dominant_matched_rate", "dominant_count_mae", "dominant_exact_rate")


def counting_compact(counting: pd.DataFrame, decimals: int = 2) -> Table | None:
    """The counting table's main columns (matched GT patterns, their count error and exact
    rate; the dominant pattern's); within a dataset the best in bold."""
    if counting is None or counting.empty:
        return None
    cols = [c for c in COUNTING_COLUMNS if c in counting.columns]
    df = counting[cols].reset_index(drop=True)
    bold = pd.DataFrame(False, index=df.index, columns=cols)
    for c in cols:
        if c in ("count_mae", "dominant_count_mae", "exact_rate", "dominant_exact_rate",
                 "dominant_matched_rate"):
            hi = not c.endswith("mae")
            bold[c] = df.groupby("dataset", sort=False)[c].transform(
                lambda s: _best_mask(s, decimals, hi)).astype(bool) if "dataset" in df else \
                _best_mask(df[c], decimals, hi)
    return Table(format_frame(df, decimals), bold, text=["dataset", "method"])


def plain_table(df: pd.DataFrame, decimals: int = 2, text: Sequence[str] = (),
                wrap: Sequence[str] = ()) -> Table:
    """Any table, human headers, numbers formatted; string columns left-aligned."""
    text = list(text) + [c for c in df.columns if df[c].dtype == object and c not in wrap]
    return Table(format_frame(df, decimals).reset_index(drop=True), text=text, wrap=wrap)
