"""The paper's tables and curves over all datasets of a run (built on
:mod:`rescu.evaluation.core`, ``count_table``, ``vpd``, ``ts`` and ``plots``), written as TSV
(numbers) and Markdown (people).

Each ``*_tables`` function takes the datasets to evaluate as ``{name: DatasetRef}`` and
the results folder where the per-image predictions of each method live
(``<results>/<dataset>/<method folder>/<image stem>.json``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import pandas as pd

from . import core as E
from . import count_table as EC
from . import plots as EP
from . import ts as ET
from . import vpd as EV
from ..io import atomic_path, read_result
from ..names import METHOD_LABELS, METHODS
from .metrics import TABLE_METRICS

# Table label -> folder of per-image predictions under <results>/<dataset>/.
NO_RP_TRUTH = ("_no ground truth: no dataset of this run has recurring-pattern annotations "
               "(annotations.json)_\n")
NO_VP_TRUTH = ("_no ground truth: no dataset of this run has vanishing-point annotations "
               "(vanishing_points.json, or vp_truth)_\n")
RP_METHODS = {METHOD_LABELS[m]: m for m in reversed(METHODS)}  # GRASP first, as in the paper
VP_METHODS = {"RESCU (AC)": "scene", "RESCU (no AC)": "scene-noac", "LSD lines": "vp-lsd",
              "RESCU joint": "scene-joint", "RESCU joint (true focal)": "scene-joint-f",
              "lu-vp-detect (true focal)": "vp-lu"}
"""VPD table rows -> per-image folders: the RP-only VP with and without the angular
constraint (scene step), the LSD-line baseline, the joint estimator (RP rows + lines,
focal estimated, the final JSON's VP; and with the dataset's true focal) and the peer
``lu-vp-detect`` (given the true focal)."""


@dataclass
class DatasetRef:
    """A dataset of the run: its folder (ground truth) and the image names processed
    (``images/<file>`` as in the annotations)."""

    root: Path
    images: list[str]
    vp_truth: Path | None = None
    """The VP ground truth file (None: ``root / "vanishing_points.json"``)."""


def _with_dataset(t: pd.DataFrame, name: str) -> pd.DataFrame:
    """``t`` with a first column ``dataset`` = ``name`` (the configured dataset name)."""
    t = t.drop(columns="dataset", errors="ignore")
    t.insert(0, "dataset", name)
    return t


def _write(df: pd.DataFrame, md: str, tsv_path: str | Path, md_path: str | Path) -> None:
    E.write_tsv(df, tsv_path)
    E.write_markdown(md, md_path)


def _pred_dirs(results: Path, ds: str, methods: Mapping[str, str]) -> dict[str, Path]:
    return {label: results / ds / folder for label, folder in methods.items()}


def rp_tables(datasets: Mapping[str, DatasetRef], results: str | Path, params: E.EvaluationParams,
              out_tsv: str | Path, out_md: str | Path, out_scores: str | Path,
              out_curves: str | Path, figures_dir: str | Path,
              methods: Mapping[str, str] = RP_METHODS) -> None:
    """RP discovery (GRASP, RESCU-I, RESCU-II) per dataset and subset, mean ± std with
    paired tests; per-image scores; metric-vs-h curves (TSV + one PNG per dataset)."""
    results = Path(results)
    frames, curves = [], []
    for name, ref in datasets.items():
        dirs = _pred_dirs(results, name, methods)
        frames.append(E.evaluate_rp_dataset(ref.root, dirs, params.iod_h, params.min_rp_precision,
                                            images=ref.images).assign(dataset=name))
        c = E.metric_curves(ref.root, dirs, params.h_curve, params.min_rp_precision,
                            images=ref.images).assign(dataset=name)
        EP.plot_metric_curves(c, Path(figures_dir) / f"rp_curves_{name}.png",
                             title=f"{name}: metrics vs IOD threshold h")
        curves.append(c)
    scores = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    E.write_tsv(scores, out_scores)
    E.write_tsv(pd.concat(curves, ignore_index=True) if curves else pd.DataFrame(), out_curves)
    summary = E.summary_table(scores, TABLE_METRICS) if len(scores) else pd.DataFrame()
    md = (E.summary_markdown(summary, TABLE_METRICS, alpha=params.significance_alpha,
                             decimals=params.decimals,
                             title=f"RP discovery (IOD h = {params.iod_h})",
                             note=E.RP_TABLE_NOTE)
          if len(summary) else NO_RP_TRUTH)
    _write(summary, md, out_tsv, out_md)


def ablation_tables(datasets: Mapping[str, DatasetRef], results: str | Path,
                    variants: Sequence[str], params: E.EvaluationParams,
                    out_tsv: str | Path, out_md: str | Path) -> None:
    """The stage-I ablation: one block per dataset, one row per variant (adaptive parameters, orientation mode)."""
    results = Path(results)
    tables, mds = [], []
    for name, ref in datasets.items():
        dirs = {v: results / name / "ablation" / v for v in variants}
        t = E.ablation_table(ref.root, dirs, params.iod_h, params.min_rp_precision,
                             images=ref.images)
        t = _with_dataset(t, name)
        tables.append(t)
        mds.append(E.summary_markdown(t, alpha=params.significance_alpha,
                                      decimals=params.decimals, row_label="adaptive",
                                      title=f"Stage-I ablation, {name}"))
    df = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    _write(df, "\n".join(mds) or "_no ablation dataset_\n", out_tsv, out_md)


def stage2_ablation_tables(datasets: Mapping[str, DatasetRef], results: str | Path,
                           variants: Sequence[str], params: E.EvaluationParams,
                           out_tsv: str | Path, out_md: str | Path) -> None:
    """The stage-II ablation: RESCU-I (its input), RESCU-II with the configured
    ``stage2`` section, and RESCU-II under each variant
    (``<results>/<dataset>/stage2-ablation/<variant>/``), per dataset and subset."""
    results = Path(results)
    frames = []
    for name, ref in datasets.items():
        dirs = {"RESCU-I": results / name / "rescu-i", "RESCU-II": results / name / "rescu-ii"}
        dirs.update({f"RESCU-II[{v}]": results / name / "stage2-ablation" / v
                     for v in variants})
        frames.append(E.evaluate_rp_dataset(ref.root, dirs, params.iod_h,
                                            params.min_rp_precision,
                                            images=ref.images).assign(dataset=name))
    scores = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    summary = E.summary_table(scores) if len(scores) else pd.DataFrame()
    md = (E.summary_markdown(summary, alpha=params.significance_alpha,
                             decimals=params.decimals,
                             title=f"Stage-II ablation (IOD h = {params.iod_h})")
          if len(summary) else "_no stage-II ablation dataset_\n")
    _write(summary, md, out_tsv, out_md)


COUNTING_NOTE = (
    "`n_matched`, `count_mae`, `exact_rate`: one row per ground-truth RP that a detected "
    "RP is accepted for (IOD), counted by the accepted detected RP with the most "
    "instances. `*_all_rps`: one row per accepted detected RP (a GT RP split into two "
    "RPs, or an object part found as its own RP, adds rows that are usually short). "
    "`dominant_*`: the image's dominant RP.\n\n")


def counting_tables(datasets: Mapping[str, DatasetRef], results: str | Path,
                    params: E.EvaluationParams, out_tsv: str | Path, out_md: str | Path,
                    methods: Mapping[str, str] = {"RESCU-I": "rescu-i", "RESCU-II": "final"},
                    ) -> None:
    """Counting: count MAE and exact-count rate of matched and dominant RPs, with the
    RP- and instance-level precision / recall (the paper's grocery table)."""
    results = Path(results)
    tables = []
    for name, ref in datasets.items():
        t = EC.counting_table(ref.root, _pred_dirs(results, name, methods), params.iod_h,
                             params.min_rp_precision, images=ref.images)
        tables.append(_with_dataset(t, name))
    df = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    md = ("## Counting\n\n" + COUNTING_NOTE + E.frame_markdown(df, params.decimals)) \
        if len(df) else \
        NO_RP_TRUTH
    _write(df, md, out_tsv, out_md)


def vp_tables(datasets: Mapping[str, DatasetRef], results: str | Path, params: E.EvaluationParams,
              out_tsv: str | Path, out_md: str | Path, out_errors: str | Path,
              out_tests: str | Path, figures_dir: str | Path,
              methods: Mapping[str, str] = VP_METHODS, out_aa: str | Path | None = None,
              out_triplet: str | Path | None = None) -> None:
    """VPD success rates (point- and vector-based) vs threshold, per dataset and method,
    with paired tests between methods; curves as PNG; the angular accuracy AA@t of the
    dominant VP and of the triplet (true and nominal focal) into ``out_aa``, the
    triplet's per-GT-VP errors into ``out_triplet``."""
    results = Path(results)
    frames, triplets = [], []
    for name, ref in datasets.items():
        dirs = _pred_dirs(results, name, methods)
        frames.append(EV.vp_frame(ref.root, dirs, images=ref.images, truth=ref.vp_truth)
                      .assign(dataset=name))
        triplets.append(EV.vp_triplet_frame(ref.root, dirs, images=ref.images,
                                            truth=ref.vp_truth).assign(dataset=name))
    errors = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    triplet = pd.concat(triplets, ignore_index=True) if triplets else pd.DataFrame()
    aa = EV.vp_aa_table(errors, triplet, params.vp_aa_thresholds) if len(errors) else \
        pd.DataFrame()
    E.write_tsv(errors, out_errors)
    if out_aa is not None:
        E.write_tsv(aa, out_aa)
    if out_triplet is not None:
        E.write_tsv(triplet, out_triplet)
    if len(errors):
        success = EV.vp_success_table(errors, params.vp_px_thresholds, params.vp_deg_thresholds)
        tests = EV.vp_significance(errors)
        for name in datasets:
            s = success[success["dataset"] == name]
            if len(s):
                EP.plot_vp_curves(s, Path(figures_dir) / f"vpd_{name}.png",
                                 title=f"{name}: VP success rate")
        md = EV.vp_markdown(success, params.decimals, errors)
        if len(aa):
            md += "\n" + EV.vp_aa_markdown(aa, params.decimals)
        if len(tests):
            md += "\n\nPaired Wilcoxon tests of per-image errors:\n\n" + \
                E.frame_markdown(tests, 4)
    else:
        success, tests = pd.DataFrame(), pd.DataFrame()
        md = NO_VP_TRUTH
    E.write_tsv(tests, out_tests)
    _write(success, md, out_tsv, out_md)


def ts_tables(datasets: Mapping[str, DatasetRef], results: str | Path, params: E.EvaluationParams,
              out_tsv: str | Path, out_md: str | Path, figures_dir: str | Path,
              methods: Mapping[str, str] = {"RESCU-II": "final"}) -> None:
    """Translation symmetry: SR_ts swept over t in (0, 0.15] and (0, 1]; on synthetic data
    also TPR on equally spaced and FPR on unequally spaced RPs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = Path(results)
    sweeps = []
    for name, ref in datasets.items():
        fr = ET.ts_frame(ref.root, _pred_dirs(results, name, methods), params.iod_h,
                        params.min_rp_precision, images=ref.images)
        for label, ts in (("fine", params.ts_t_fine), ("coarse", params.ts_t_coarse)):
            s = ET.ts_sweep(fr, ts, params.ts_which).assign(dataset=name, sweep=label)
            sweeps.append(s)
    df = pd.concat(sweeps, ignore_index=True) if sweeps else pd.DataFrame()
    if len(df):
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        for ax, label in zip(axes, ("fine", "coarse")):
            for (ds, m), g in df[df["sweep"] == label].groupby(["dataset", "method"]):
                ax.plot(g["t"], g["sr_ts"], marker=".", label=f"{ds} {m}")
            ax.set_xlabel("tolerance t on |cr - 4/3|")
            ax.set_ylabel("SR_ts")
            ax.set_ylim(0, 1.02)
            ax.legend(fontsize=7)
        fig.tight_layout()
        png = Path(figures_dir) / "ts_sweep.png"
        with atomic_path(png) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
        md = "## Translation symmetry (SR_ts vs t)\n\n" + E.frame_markdown(
            df[df["sweep"] == "fine"], params.decimals)
    else:  # photos only: the declared figure says so (a job must write its outputs)
        fig = plt.figure(figsize=(5, 1))
        fig.text(0.5, 0.5, "no ground truth: no translation-symmetry sweep", ha="center",
                 va="center")
        with atomic_path(Path(figures_dir) / "ts_sweep.png") as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
        md = NO_RP_TRUTH
    _write(df, md, out_tsv, out_md)


def result_rows(final_jsons: Mapping[str, Sequence[str | Path]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Captions and failures tables from the final per-image JSONs ``{dataset: [paths]}``.

    Returns ``(captions, failures)``: captions with ``dataset, image, n_patterns,
    dominant_count, base, enhanced``; failures with ``dataset, image, stage, type,
    message`` (one row per image that failed somewhere).
    """
    caps, fails = [], []
    for ds, paths in final_jsons.items():
        for p in paths:
            r = read_result(p)
            f = r.extra.get("failure")
            if f:
                fails.append({"dataset": ds, "image": r.image, "stage": f.get("stage"),
                              "type": f.get("type"), "message": f.get("message")})
            dom = next((q for q in r.patterns if q.id == r.dominant_pattern), None)
            caps.append({"dataset": ds, "image": r.image, "n_patterns": len(r.patterns),
                         "dominant_count": dom.count if dom else 0,
                         "base": (r.caption or {}).get("base", ""),
                         "enhanced": (r.caption or {}).get("enhanced", "")})
    cols_f = ["dataset", "image", "stage", "type", "message"]
    return pd.DataFrame(caps), pd.DataFrame(fails, columns=cols_f)


def summary_markdown(parts: Sequence[tuple[str, str | Path]], header: str) -> str:
    """Concatenate Markdown tables ``[(heading, md_path)]`` under a header."""
    out = [header, ""]
    for heading, path in parts:
        out += [f"# {heading}", "", Path(path).read_text().strip(), ""]
    return "\n".join(out) + "\n"


def dataset_refs(table: Mapping[str, Mapping[str, Any]], names: Sequence[str]) -> dict[str, DatasetRef]:
    """:class:`DatasetRef` for the named datasets of an image table
    (:func:`rescu.data.datasets.build_image_table`)."""
    return {n: DatasetRef(Path(table[n]["root"]), sorted(dict(table[n]["names"]).values()),
                          Path(table[n]["vp_truth"]) if table[n].get("vp_truth") else None)
            for n in names}


def failures_markdown(failures: pd.DataFrame) -> str:
    """The failures table in Markdown (or a line saying there were none)."""
    if not len(failures):
        return "## Failures\n\nNo image failed.\n"
    return "## Failures\n\n" + E.frame_markdown(failures) + "\n"


def summary_header(backbone: str) -> str:
    """The header of ``summary.md``: what produced the tables."""
    from .. import __version__

    return (f"# RESCU {__version__}: tables\n\nStage-II backbone: **{backbone or 'n/a'}** "
            f"(frozen, ImageNet weights). Metrics: IOD protocol of `rescu.evaluation.metrics`; mean ± std "
            f"over images; bold = best, italics = not significantly different from the best "
            f"(paired Wilcoxon).\n")
