"""Planned job counts of `make run` and `make paper`, from Snakemake dry runs.

    python benchmarks/speed/job_counts.py [--rules] [--config KEY=VALUE ...]

Each plan is made into a fresh temporary results folder (so it counts every job, not
what a finished run still lacks), with ``../shared/data`` as it is on this machine:
without it, `make run` is the synthetic benchmark and the package photos only. Prints
the total per plan and, with ``--rules``, the count per rule. Writes nothing in the
checkout but the code stamps of the temporary results folders (which are removed).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
PLANS = {"make run": [], "make paper": ["--configfile", str(REPO / "config" / "paper.yaml")]}


def plan(args: list[str], config: list[str]) -> dict[str, int]:
    """Job count per rule of a dry run with ``args`` and ``--config`` items ``config``
    (``{"total": n, rule: n, ...}``)."""
    with tempfile.TemporaryDirectory(prefix="rescu-plan-") as tmp:
        cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "-n", "--cores", "2", *args,
               "--config", *config, f"results_dir={tmp}/results"]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        sys.exit(f"snakemake -n failed:\n{proc.stderr[-3000:]}")
    text = proc.stdout + proc.stderr
    table = text[text.index("Job stats:"):] if "Job stats:" in text else ""
    counts = {m.group(1): int(m.group(2))
              for m in re.finditer(r"^([\w-]+)\s+(\d+)$", table, re.M)}
    return counts


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rules", action="store_true", help="also the count per rule")
    ap.add_argument("--config", nargs="+", default=[], metavar="KEY=VALUE",
                    help="Snakemake --config items for both plans, e.g. run_datasets=synthetic")
    a = ap.parse_args(argv)
    data = REPO.parent / "shared" / "data"
    print(f"../shared/data {'present' if data.is_dir() else 'absent'}")
    for name, args in PLANS.items():
        counts = plan(args, a.config)
        print(f"{name}: {counts.get('total', 0)} jobs")
        if a.rules:
            for rule, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
                if rule != "total":
                    print(f"  {rule:28s} {n:5d}")


if __name__ == "__main__":
    main()
