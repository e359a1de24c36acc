"""Command-line pieces shared by the benchmark scripts that read a finished run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable


def run_parser(doc: str) -> argparse.ArgumentParser:
    """Parser with the arguments of a script over one dataset of a finished run:
    ``results`` (its results folder), ``--dataset`` (default synthetic) and ``--config``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", default="synthetic")
    ap.add_argument("--config", type=Path, default=None,
                    help="config file merged over the defaults (rescu/defaults/config.yaml)")
    return ap


def sets_parser(doc: str, method: str = "rescu-ii") -> argparse.ArgumentParser:
    """Parser of a study over several datasets of a finished run: ``results``,
    ``--dataset`` (repeatable, into ``datasets``; None: the caller's default), ``--config``
    and ``--method`` (the per-image JSON folder, default ``method``)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", action="append", dest="datasets", default=None,
                    help="a dataset of the run (repeat for several; default synthetic)")
    ap.add_argument("--config", type=Path, default=None,
                    help="config file merged over the defaults (rescu/defaults/config.yaml)")
    ap.add_argument("--method", default=method, help="per-image JSON folder")
    return ap


def set_predictions(ap: argparse.ArgumentParser, a: argparse.Namespace
                    ) -> list[tuple[str, Path, Path]] | None:
    """``(dataset, dataset folder, prediction folder)`` for each dataset of a
    :func:`sets_parser` command line (``a.datasets``, default synthetic; predictions in
    ``<results>/<dataset>/<method>/``); None, with a message, when one lacks its ground
    truth or its predictions."""
    out = []
    for ds in a.datasets or ["synthetic"]:
        a.dataset = ds
        _, data = run_dataset(ap, a)
        pred = a.results / ds / a.method
        if not inputs_present((data / "annotations.json", "ground truth"),
                              (pred, "predictions")):
            return None
        out.append((ds, data, pred))
    return out


def variants_parser(doc: str) -> argparse.ArgumentParser:
    """Parser of a study that re-runs one step with ``--set KEY=VALUE`` on a finished run:
    ``results``, ``--dataset`` (repeatable), ``--config``, ``--set``, ``--name``,
    ``--workers``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", action="append", default=[], help="repeatable")
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--name", default=None)
    ap.add_argument("--workers", type=int, default=1)
    return ap


def print_side_by_side(data: Path, folders: dict[str, Path], dataset: str) -> None:
    """The RP metrics (mean ± std over the images with a result in every folder) of each
    folder of per-image results, by row label; with two folders also the paired
    Wilcoxon p-value of each metric (all images)."""
    from rescu.evaluation.core import (evaluate_rp_dataset, frame_markdown, significance_table,
                                       summary_markdown, summary_table)
    from rescu.evaluation.metrics import TABLE_METRICS as metrics

    images = images_with(data, *folders.values())
    if not images:
        print(f"{dataset}: no image with results in {', '.join(map(str, folders.values()))}")
        return
    df = evaluate_rp_dataset(data, folders, images=images)
    df["dataset"] = dataset
    print("\n" + summary_markdown(summary_table(df, metrics), metrics, decimals=3))
    if len(folders) == 2:
        sig = significance_table(df, metrics)
        sig = sig[sig.subset == "all"]
        print(frame_markdown(sig[["metric", "n_pairs", "mean_a", "mean_b", "p_value"]],
                             decimals=3))


def run_dataset(ap: argparse.ArgumentParser, a: argparse.Namespace
                ) -> tuple[dict[str, Any], Path]:
    """``(config, dataset folder)`` of ``a.dataset`` as the run saw them; a dataset that is
    not in the config is a usage error."""
    from rescu.config import load_config
    from rescu.data.datasets import dataset_root

    cfg = load_config(a.config)
    if a.dataset not in cfg["datasets"]:
        ap.error(f"dataset {a.dataset!r} is not in the config ({', '.join(cfg['datasets'])})")
    return cfg, dataset_root(a.dataset, cfg["datasets"][a.dataset], str(a.results))


def print_rows(df: Any) -> None:
    """Print a DataFrame whole (every row, wide lines, 2 decimals), without its index."""
    import pandas as pd

    with pd.option_context("display.width", 250, "display.max_rows", None):
        print(df.round(2).to_string(index=False))


def claim_variant_folder(out: Path, record: dict[str, Any]) -> bool:
    """Create ``out`` for a variant made with the settings ``record`` (saved as
    ``out/params.json``); False, with a message, when ``out`` was made with other settings
    (its results must not be mixed with these)."""
    import json
    import sys

    from rescu.io import write_json

    out.mkdir(parents=True, exist_ok=True)
    pfile = out / "params.json"
    if pfile.exists() and json.loads(pfile.read_text()) != json.loads(json.dumps(record)):
        print(f"{out}: made with other settings ({pfile}); choose another --name or --out",
              file=sys.stderr)
        return False
    write_json(pfile, record)
    return True


def run_jobs(fn: Callable[[Any], Any], jobs: list[Any], workers: int) -> list[Any]:
    """``fn`` over ``jobs``: in ``workers`` spawned processes when more than one (results
    in completion order), else in this process in order."""
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            return list(pool.imap_unordered(fn, jobs))
    return [fn(j) for j in jobs]


def inputs_present(*needed: tuple[Path, str]) -> bool:
    """Whether every ``(path, what)`` of ``needed`` exists; for the first that does not,
    says ``<path>: no <what> (run the pipeline first)`` on stderr and returns False."""
    for path, what in needed:
        if not path.exists():
            print(f"{path}: no {what} (run the pipeline first)", file=sys.stderr)
            return False
    return True


def check_run_datasets(ap: argparse.ArgumentParser, cfg: dict[str, Any], results: Path,
                       sets: list[str], folder: str) -> bool:
    """Each of ``sets`` is a dataset of the config (else a usage error) with
    ``<results>/<dataset>/<folder>`` made by a run; False (and a message) when one is
    missing."""
    for ds in sets:
        if ds not in cfg["datasets"]:
            ap.error(f"dataset {ds!r} is not in the config")
    for ds in sets:
        if not (results / ds / folder).is_dir():
            print(f"{results / ds / folder}: not found (run the pipeline first)",
                  file=sys.stderr)
            return False
    return True


def images_with(data: Path, *folders: Path) -> list[str]:
    """File names of ``data/annotations.json`` with a ``<stem>.json`` in every folder, in
    the annotations' order."""
    import json

    have = None
    for d in folders:
        stems = {p.stem for p in d.glob("*.json") if p.name != "params.json"}
        have = stems if have is None else have & stems
    ann = json.loads((data / "annotations.json").read_text())
    return [im["file_name"] for im in ann["images"]
            if Path(im["file_name"]).stem in (have or set())]


def parse_sets(items: list[str]) -> dict[str, Any]:
    """``["KEY=VALUE", ...]`` -> ``{KEY: YAML value}``; ValueError on an item without '='."""
    import yaml

    out: dict[str, Any] = {}
    for it in items:
        key, sep, val = it.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {it!r}: expected KEY=VALUE")
        out[key.strip()] = yaml.safe_load(val)
    return out


def f1(precision: float, recall: float) -> float:
    """F1 of a mean precision and a mean recall (the studies' one-number summary of a set's
    any-RP instance figures); 0 when both are 0."""
    return float(2 * precision * recall / (precision + recall + 1e-9))
