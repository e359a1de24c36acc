# What every rule file needs: the image table built once from the config, wildcard
# constraints, the library files each rule depends on, and the final targets.
import sys
from pathlib import Path

from rescu.data.datasets import PHOTOS_DIR, SYNTHETIC_DIR, build_image_table, skipped_datasets
from rescu.extension.params import PREDICT_SECTION
from rescu.data.synth import synthetic_image_names
from rescu.discovery.ablation import SOURCE_ROWS
from rescu.discovery.sources import dense_step_section
from rescu_workflow.code_deps import PACKAGE_DIR, step_dependencies
from rescu.names import METHODS

RESULTS = config["results_dir"]
PAPER = bool(config.get("paper", False))  # also the ablations and their tables (make paper)
DENSE = bool(config["dense"]["enabled"])  # the dense RP source (rule dense) feeds RESCU-I
# the dense step's parameters: what finds the dense RPs, not whether or how RESCU-I takes
# them (rescu.discovery.sources.DENSE_STEP_FIXED: switching dense.enabled or dense.mode, or
# changing how RESCU-I scores stage I's RPs or which RPs it sets aside as one structure or
# as a board's squares, reruns no dense or ablation job)
DENSE_STEP = dense_step_section(config["dense"])
# the stage-I ablation's source rows (sparse-only, dense-only, sparse+dense; they need the dense step)
ABLATION_SOURCES = bool(config["ablation"].get("sources", True))
LOGS = f"{RESULTS}/logs"  # per-step logs live with the results they belong to
BASEDIR = Path(workflow.basedir)

wildcard_constraints:
    dataset=r"[A-Za-z0-9_\-]+",
    image=r"[^/]+",
    method="|".join(METHODS),


# dataset name -> {"root": folder with images/ (+ ground truth), "images": {stem: path},
#                  "kind": ..., "has_rps": bool, "has_vps": bool}
DATASETS = build_image_table(config, results_dir=RESULTS, log=lambda m: None)
# dataset name -> why it is not in this run (its folder is missing or holds no images):
# one line on the terminal, and the report names each with its reason
SKIPPED = skipped_datasets(config, results_dir=RESULTS)
if SKIPPED:
    print(f"rescu: not in this run (folder missing or without images): "
          f"{', '.join(SKIPPED)}; the report says why and how to add a dataset",
          file=sys.stderr)


CODE_DIR = f"{RESULTS}/.code"
RUN_STEP = BASEDIR / "workflow" / "run_step.py"


def step_params(script, **params):
    """The ``params`` of a per-image rule that runs ``workflow/scripts/<script>.py``
    (``params: **step_params(script, name=value, ...)`` with ``shell: STEP_SHELL``): the
    rule's parameters as they are, which Snakemake records and compares to rerun a job
    whose parameters changed, and ``step``, a function Snakemake calls per job that
    gives the command running the script: the Python running Snakemake runs it through
    ``workflow/run_step.py`` with the job as JSON (the named inputs and outputs, the
    parameters, threads and wildcards), as ``script:`` would but without importing
    Snakemake in the job (a job that does nothing: 0.19-0.24 s instead of 0.26-0.30 s,
    ``benchmarks/speed/job_overhead.py``); the script reads ``snakemake.params.<name>``
    as under ``script:``. ``params``: JSON values
    (config sections), or functions of the wildcards giving one.

    With ``step_server.enabled`` the command is ``python -m rescu_workflow.step_server
    --idle=SECONDS run_step.py ...``: the job runs in a child of the step server, which
    has already imported its libraries (:mod:`rescu_workflow.step_server`).

    Snakemake does not record a function's value as a parameter, nor a command's paths
    as code (``STEP_SHELL`` is the rule's code, the same text wherever the checkout or
    the Python lives); the script, the runner and the library files it runs are the
    rule's code input (:func:`step_code`)."""
    import json
    import shlex

    path = BASEDIR / "workflow" / "scripts" / f"{script}.py"
    if not path.is_file():
        raise ValueError(f"step_params: no workflow script {path}")
    if "step" in params:
        raise ValueError("step_params: 'step' is the parameter it adds")
    server = config["step_server"]
    runner = [sys.executable, RUN_STEP]
    if server["enabled"]:  # the command only: a switch that changes no output reruns no job
        runner[1:1] = ["-m", "rescu_workflow.step_server",
                       f"--idle={float(server['idle_seconds']):g}"]
    head = " ".join(shlex.quote(str(a)) for a in (*runner, path))

    def step(wildcards, input, output, threads):
        def named(files):
            return {"items": [str(f) for f in files],
                    "names": {k: list(v) for k, v in files._names.items()}}

        values = {k: v(wildcards) if callable(v) else v for k, v in params.items()}
        job = json.dumps({"input": named(input), "output": named(output), "params": values,
                          "threads": threads, "wildcards": dict(wildcards.items())},
                         separators=(",", ":"))
        return f"{head} {shlex.quote(job)}"

    return {**params, "step": step}


# the shell: of every rule with step_params; {log:q}: Snakemake quotes the log's path
STEP_SHELL = "{params.step} {log:q}"

# Scheduling priorities (rule ``priority:``; 0 for the others): among the jobs ready to run,
# Snakemake starts those of higher priority first. An image's chain of jobs is long
# (prepare, dense, rescu_i, stage2_features, ... one after the other), and a run whose last
# image is prepared late ends with that image's chain running alone on one core while the
# other idles. Every image is prepared first, then the long jobs and those that unblock
# them run; the short per-image jobs (scene, VPs, captions, overlays) and the tables fill
# the cores at the end. Priorities order the jobs only: they change no output and no
# job's parameters.
PRIORITY = {
    "prepare": 4,
    "dense": 3,
    "features": 3,
    "rescu_i": 2,
    "stage2_features": 2,
    "stage2_ablation": 2,
    "ablation": 1,
}


def step_code(script):
    """The code input of a rule that runs ``workflow/scripts/<script>.py``: one stamp file,
    ``<results>/.code/<script>.txt``, listing with their SHA-256 every rescu/ source file
    the script runs (the script's imports and those inside the step functions it calls,
    closed over the package's imports: :func:`rescu_workflow.code_deps.step_dependencies`), the
    script itself and ``workflow/run_step.py`` (which runs the per-image rules' scripts,
    :func:`step_params`; Snakemake itself tracks a ``script:``, not a ``shell:``'s).

    The stamp is written here, while the workflow is read, and only when its text
    changes: editing one of those files gives the stamp a new time, which reruns the
    rules that read it; anything else leaves it alone. (It used to be a rule's output:
    a job per script, each reading the whole workflow again in its own process.) One stamp
    instead of the files themselves keeps Snakemake from checking a dozen source files
    for every waiting job whenever it schedules."""
    import hashlib
    import os

    path = BASEDIR / "workflow" / "scripts" / f"{script}.py"
    if not path.is_file():
        raise ValueError(f"step_code: no workflow script {path}")
    text = "".join(f"{hashlib.sha256(f.read_bytes()).hexdigest()}  "  # rescu/<module>.py,
                   f"{f.relative_to(PACKAGE_DIR.parent).as_posix()}\n"  # wherever installed
                   for f in step_dependencies(path))
    text += "".join(f"{hashlib.sha256(f.read_bytes()).hexdigest()}  "
                    f"{f.relative_to(BASEDIR).as_posix()}\n" for f in (path, RUN_STEP))
    stamp = Path(CODE_DIR) / f"{script}.txt"
    if not stamp.is_file() or stamp.read_text() != text:
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_name(f".{stamp.name}.{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, stamp)  # whole or not at all, also when two readers race
    return [str(stamp)]


def stage2_upstream():
    """The ``stage2`` sections of the features and training steps: all but ``predict``
    (:data:`rescu.extension.params.PREDICT_SECTION`, the keys that act only in prediction),
    so that a change of a prediction gate reruns prediction only."""
    return {k: v for k, v in config["stage2"].items() if k != PREDICT_SECTION}


def _stage2_ablation_split():
    """``stage2_ablation.variants`` split in two: those that need features and a head of their
    own (rule ``stage2_ablation``), and those that, merged into ``stage2``, change only its
    ``predict`` section (their prediction-only form,
    :func:`rescu.extension.params.as_predict_variant`): the run's own features and head give
    those (rule ``stage2_predict_ablation``), with no backbone pass or training of their own."""
    from rescu.extension.params import as_predict_variant

    own, pred = {}, {}
    for name, over in config["stage2_ablation"]["variants"].items():
        p = as_predict_variant(config["stage2"], over)
        if p is None:
            own[name] = over
        else:
            pred[name] = p
    return own, pred


_STAGE2_OWN, _STAGE2_PREDICT_ONLY = _stage2_ablation_split()  # once, when the workflow is read


def stage2_ablation_variants():
    """The stage-II ablation variants that need their own features and head (rule
    ``stage2_ablation``)."""
    return _STAGE2_OWN


def stage2_predict_variants():
    """The variants rule ``stage2_predict_ablation`` computes from the run's own features and
    head: ``stage2_ablation.predict_variants`` (the ``predict`` section only, names other than
    those of ``stage2_ablation.variants``: checked once with the whole config by
    :func:`rescu.config.validate_config` in the Snakefile), and the ``variants`` that change
    nothing but prediction (:func:`_stage2_ablation_split`)."""
    return {**(config["stage2_ablation"].get("predict_variants") or {}),
            **_STAGE2_PREDICT_ONLY}


def stage2_ablation_rows():
    """Every stage-II ablation variant, in the table's order: ``variants``, then
    ``predict_variants``."""
    return list(config["stage2_ablation"]["variants"]) + \
        list(config["stage2_ablation"].get("predict_variants") or {})


def images(dataset):
    return sorted(DATASETS[dataset]["images"])


def source_image(wildcards):
    return DATASETS[wildcards.dataset]["images"][wildcards.image]


def per_image(pattern, datasets=None, **more):
    """Expand ``pattern`` (with {dataset}, {image} and the wildcards named in ``more``)
    over the chosen datasets' images."""
    out = []
    for ds in datasets if datasets is not None else DATASETS:
        out += expand(pattern, dataset=ds, image=images(ds), **more)
    return out


def dense_input(wildcards):
    """RESCU-I's extra input when the dense source is on: the image's dense RPs and the
    coarse feature map the dense step kept."""
    if not DENSE:
        return {}
    return {"dense": f"{RESULTS}/{wildcards.dataset}/dense/{wildcards.image}.json",
            "dense_map": f"{RESULTS}/{wildcards.dataset}/dense/{wildcards.image}.map.h5"}


def dense_map_input(wildcards):
    """Stage II's prediction input when the dense source is on: the coarse feature map the
    dense step kept (RESCU-II keeps one box per object, as RESCU-I does)."""
    if not DENSE:
        return {}
    return {"dense_map": f"{RESULTS}/{wildcards.dataset}/dense/{wildcards.image}.map.h5"}


def rp_methods():
    """Result folders of the RP discovery table, by row label (the dense source's own row
    when it is on)."""
    from rescu.evaluation.tables import RP_METHODS

    return {**RP_METHODS, "Dense source": "dense"} if DENSE else dict(RP_METHODS)


def rp_datasets():
    return [d for d, v in DATASETS.items() if v["has_rps"]]


def vp_datasets():
    return [d for d, v in DATASETS.items() if v["has_vps"]]


def ablation_variants():
    """Rows of the stage-I ablation: the configured variants, then (``ablation.sources``)
    the source rows of ``rescu.discovery.ablation.SOURCE_ROWS``."""
    extra = list(SOURCE_ROWS) if ABLATION_SOURCES else []
    return list(config["ablation"]["variants"]) + extra


def ablation_dense_input(wildcards):
    """The ablation step's extra input with ``ablation.sources``: the image's dense RPs."""
    if not ABLATION_SOURCES:
        return {}
    return {"dense": f"{RESULTS}/{wildcards.dataset}/dense/{wildcards.image}.json"}


def ablation_datasets():
    return [d for d in config["ablation"]["datasets"] if d in DATASETS and DATASETS[d]["has_rps"]]


def stage2_ablation_datasets():
    return [d for d in config["stage2_ablation"]["datasets"]
            if d in DATASETS and DATASETS[d]["has_rps"]]


def prepared(wildcards=None):
    return {
        "png": f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        "meta": f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
    }


def final_targets():
    t = per_image(f"{RESULTS}/{{dataset}}/final/{{image}}.json")
    t += per_image(f"{RESULTS}/{{dataset}}/overlay/{{image}}.png")
    t += [f"{RESULTS}/tables/summary.md", f"{RESULTS}/report/index.html"]
    t += per_image(f"{RESULTS}/{{dataset}}/vp-lsd/{{image}}.json", vp_datasets())
    return t
