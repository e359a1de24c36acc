"""Command-line pieces shared by the benchmark scripts that read a finished run."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def run_parser(doc: str) -> argparse.ArgumentParser:
    """Parser with the arguments of a script over one dataset of a finished run:
    ``results`` (its results folder), ``--dataset`` (default synthetic) and ``--config``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", default="synthetic")
    ap.add_argument("--config", type=Path, default=None,
                    help="config file (default config/config.yaml)")
    return ap


def run_dataset(ap: argparse.ArgumentParser, a: argparse.Namespace
                ) -> tuple[dict[str, Any], Path]:
    """``(config, dataset folder)`` of ``a.dataset`` as the run saw them; a dataset that is
    not in the config is a usage error."""
    from rescu.config import load_config
    from rescu.datasets import dataset_root

    cfg = load_config(a.config)
    if a.dataset not in cfg["datasets"]:
        ap.error(f"dataset {a.dataset!r} is not in the config ({', '.join(cfg['datasets'])})")
    return cfg, dataset_root(a.dataset, cfg["datasets"][a.dataset], str(a.results))


def print_rows(df: Any) -> None:
    """Print a DataFrame whole (every row, wide lines, 2 decimals), without its index."""
    import pandas as pd

    with pd.option_context("display.width", 250, "display.max_rows", None):
        print(df.round(2).to_string(index=False))
