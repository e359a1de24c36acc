"""Per-job overhead of the pipeline: what a Snakemake job costs that does nothing.

    python benchmarks/speed/job_overhead.py [--jobs 20] [--results results]
                                            [--datasets cmp_facade,chess] [--rules-only]

Prints
1. the wall time per job of a no-op rule written like the pipeline's adapters (the
   script imports ``rescu.pipeline``, sets up its log, limits threads, copies its input
   to its output): ``snakemake --cores 1`` with ``--jobs`` + 1 jobs against one with 1
   job, the difference over ``--jobs`` (Snakemake's scheduling of each job included,
   its start-up not); and the seconds its ``benchmark:`` file records per job. Once as
   a ``script:`` rule, then run as the per-image rules run their scripts (``shell:``
   through ``workflow/run_step.py``, ``step_params`` in ``workflow/rules/common.smk``),
   without and with the step server (:mod:`rescu_workflow.step_server`), and the
   same two with a script that imports torch, as the steps that run the backbone do;
2. the seconds a fresh interpreter takes to import what each per-image step imports
   (median of 3);
3. with ``--results`` (a finished run), the median seconds per job of every rule, from
   the run's ``benchmarks/`` files.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

SNAKEFILE = """
rule all:
    input: expand("out/{{i}}.txt", i=range({n}))

rule noop:
    input: "in.txt"
    output: "out/{{i}}.txt"
    log: "logs/{{i}}.log"
    benchmark: "bench/{{i}}.tsv"
    script: "noop.py"
"""

# the same rule as the pipeline's per-image rules run their scripts (step_params)
STEP_SNAKEFILE = """
import json, shlex, sys

def step(wildcards, input, output, threads):
    job = {{"input": {{"items": list(input), "names": {{}}}},
           "output": {{"items": list(output), "names": {{}}}}, "params": {{}},
           "threads": threads, "wildcards": dict(wildcards.items())}}
    return " ".join(shlex.quote(a) for a in (sys.executable, *{server!r}, {runner!r},
                                             "noop.py", json.dumps(job)))

rule all:
    input: expand("out/{{i}}.txt", i=range({n}))

rule noop:
    input: "in.txt"
    output: "out/{{i}}.txt"
    params: step=step
    log: "logs/{{i}}.log"
    benchmark: "bench/{{i}}.tsv"
    shell: "{{params.step}} {{log:q}}"
"""
SCRIPT = """
import shutil
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
shutil.copy(snakemake.input[0], snakemake.output[0])
"""
# the same, as a step that runs the backbone starts: it imports torch
TORCH_SCRIPT = SCRIPT.replace("pipeline.limit_threads(snakemake.threads)",
                              "pipeline.limit_threads(snakemake.threads, torch=True)")

# form -> (Snakefile, what runs run_step.py (the step server's command), script)
SERVER = ["-m", "rescu_workflow.step_server", "--idle=30"]
FORMS = {
    "script:": (SNAKEFILE, [], SCRIPT),
    "shell: through workflow/run_step.py": (STEP_SNAKEFILE, [], SCRIPT),
    "shell: through workflow/run_step.py and the step server":
        (STEP_SNAKEFILE, SERVER, SCRIPT),
    "shell: through workflow/run_step.py, importing torch": (STEP_SNAKEFILE, [], TORCH_SCRIPT),
    "shell: through workflow/run_step.py and the step server, importing torch":
        (STEP_SNAKEFILE, SERVER, TORCH_SCRIPT),
}

STEP_IMPORTS = {
    "prepare / features": "from rescu import pipeline, io; from rescu.discovery import features",
    "stage I": "from rescu import pipeline; from rescu.discovery import stage1",
    "GRASP": "from rescu import pipeline; from rescu.discovery import grasp",
    "stage II (torch)": ("from rescu import pipeline; "
                         "from rescu.extension import proposal_features, backbone; import torch"),
    "scene": "from rescu import pipeline; from rescu.scene import analyse, completion",
    "caption": "from rescu import pipeline; from rescu.captions import caption",
    "overlay": "from rescu import pipeline, visualize",
    "tables": "from rescu.evaluation import tables, core",
}


def _run_noop(n: int, snakefile: str = SNAKEFILE, server: list[str] | None = None,
              script: str = SCRIPT) -> tuple[float, list[float]]:
    """Seconds of one ``snakemake --cores 1`` process running ``n`` no-op jobs, and the
    seconds each job's benchmark file records (``snakefile``, ``server`` (the arguments
    before run_step.py: :data:`SERVER` or none) and ``script``: one of :data:`FORMS`)."""
    with tempfile.TemporaryDirectory(prefix="rescu-noop-") as d:
        w = Path(d)
        (w / "Snakefile").write_text(snakefile.format(
            n=n, runner=str(REPO / "workflow" / "run_step.py"), server=list(server or [])))
        (w / "noop.py").write_text(script)
        (w / "in.txt").write_text("x\n")
        t0 = time.perf_counter()
        proc = subprocess.run([str(BIN / "snakemake"), "--cores", "1", "--quiet", "all"],
                              cwd=w, capture_output=True, text=True,
                              env={"PATH": f"{BIN}:/usr/bin:/bin"})
        total = time.perf_counter() - t0
        if proc.returncode:
            sys.exit(f"snakemake failed:\n{proc.stderr[-3000:]}")
        bench = [float((w / "bench" / f"{i}.tsv").read_text().splitlines()[1].split("\t")[0])
                 for i in range(n)]
        return total, bench


def noop_jobs(n: int, snakefile: str = SNAKEFILE, server: list[str] | None = None,
              script: str = SCRIPT) -> tuple[float, float]:
    """(wall seconds per job, median benchmark seconds per job) of no-op jobs: the
    difference between a run of ``n + 1`` jobs and one of 1 job, over ``n`` (Snakemake's
    start-up, DAG and scheduling of the run itself cancel out; with the step server, the
    run of 1 job starts it)."""
    one, _ = _run_noop(1, snakefile, server, script)
    many, bench = _run_noop(n + 1, snakefile, server, script)
    print(f"  (snakemake process: 1 job {one:.1f} s, {n + 1} jobs {many:.1f} s)")
    return (many - one) / n, statistics.median(bench)


def import_seconds(stmt: str, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", stmt], check=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def rule_medians(results: Path, datasets: set[str] | None = None
                 ) -> dict[str, tuple[int, float]]:
    """rule -> (jobs, median seconds) from ``results/benchmarks/<dataset>/<rule>/*.tsv``
    (only the given ``datasets`` when not None)."""
    by_rule: dict[str, list[float]] = {}
    for f in (results / "benchmarks").glob("**/*.tsv"):
        if datasets is not None and f.parent.parent.name not in datasets:
            continue
        lines = f.read_text().splitlines()
        if len(lines) > 1:
            by_rule.setdefault(f.parent.name, []).append(float(lines[1].split("\t")[0]))
    return {r: (len(v), statistics.median(v)) for r, v in sorted(by_rule.items())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=20, help="no-op jobs (default 20)")
    ap.add_argument("--results", type=Path, default=None,
                    help="a finished run's results folder: median seconds per rule")
    ap.add_argument("--datasets", default=None,
                    help="with --results: only these datasets (comma-separated)")
    ap.add_argument("--rules-only", action="store_true",
                    help="with --results: only the per-rule medians (no no-op jobs)")
    a = ap.parse_args(argv)
    if a.jobs < 1:
        ap.error("--jobs must be >= 1")
    if a.rules_only and a.results is None:
        ap.error("--rules-only needs --results")
    if a.rules_only:
        return print_rules(a.results, a.datasets)
    for form, (snakefile, server, script) in FORMS.items():
        print(f"no-op job, {form} ({a.jobs} jobs, snakemake --cores 1):")
        per_job, bench = noop_jobs(a.jobs, snakefile, server, script)
        print(f"  wall per job {per_job:.2f} s; its benchmark file records {bench:.2f} s")
    print("fresh interpreter importing what a step imports (median of 3):")
    for name, stmt in STEP_IMPORTS.items():
        print(f"  {name:<20} {import_seconds(stmt):.2f} s")
    if a.results is not None:
        print_rules(a.results, a.datasets)


def print_rules(results: Path, datasets: str | None) -> None:
    """Print :func:`rule_medians` of a run (``datasets``: comma-separated, or None)."""
    only = None if datasets is None else {d.strip() for d in datasets.split(",") if d.strip()}
    print(f"median seconds per job, {results}/benchmarks"
          + ("" if only is None else f" ({', '.join(sorted(only))})") + ":")
    for rule, (n, med) in rule_medians(results, only).items():
        print(f"  {rule:<26} {n:>5} jobs  {med:7.2f} s")


if __name__ == "__main__":
    main()
