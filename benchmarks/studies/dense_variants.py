"""The dense RP source with other settings on a finished run, scored on every image of
one or more datasets (beside the run's own dense RPs when it made them).

Re-runs the pipeline's dense step (:func:`rescu.pipeline.dense`) on each image's
prepared picture (``<results>/<dataset>/prepared/<image>.png``) with the config's
``dense`` keys overridden by ``--set KEY=VALUE`` (values read as YAML, checked by
:class:`rescu.discovery.sources.DenseParams`). Results go to
``<results>/benchmarks/dense-variants/<name>/<dataset>/<image>.json`` beside a
``params.json`` of the settings (a folder made with other settings is refused; an image
already there is not recomputed). Then prints, per dataset, the mean ± std over images
of the paper's instance precision / recall, the RP precision / recall and the any-RP
instance figures (:mod:`rescu.evaluation.metrics`) of the variant's dense RPs alone and,
when the run has a ``dense/`` folder (it ran with ``dense.enabled``), of the run's
dense RPs with the paired Wilcoxon p-value of each metric. Asserts nothing.

These are the *dense source* figures (the RP table's row of that name): RESCU-I and
RESCU-II with the variant need the pipeline run with the setting. The dense step takes
about a second per image plus the backbone's load, so the four real RP sets take a few
minutes on 2 workers.

Usage (from the repository root)::

    make realdev        # or any run of the datasets, with or without the dense source
    python benchmarks/studies/dense_variants.py results/realdev \\
        --dataset aerial_cars --dataset chess --set max_touching=4 --workers 2
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

from _cli import parse_sets  # noqa: E402


def _one(job: tuple[str, str, str, dict[str, Any]]) -> tuple[str, str, float]:
    """The dense step on one image (one thread); (stem, status, seconds)."""
    png, meta, out_json, params = job
    t = time.time()
    from rescu import pipeline

    pipeline.limit_threads(1, torch=True)
    fail = pipeline.dense(png, meta, out_json, params)
    status = "ok" if fail is None else f"failed: {fail.get('message')}"
    return Path(out_json).stem, status, time.time() - t


def main(argv: list[str] | None = None) -> int:
    from _cli import (check_run_datasets, claim_variant_folder, print_side_by_side,
                      run_jobs, variants_parser)

    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.discovery.sources import DenseParams
    from rescu.params import deep_merge

    ap = variants_parser(__doc__)
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error("--workers must be at least 1")
    cfg = load_config(a.config, stage2=False)
    try:
        over = parse_sets(a.sets)
        params = deep_merge(cfg["dense"], over)
        DenseParams.from_dict(params)
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    name = a.name or ("_".join(f"{k}={v}" for k, v in over.items()) or "config")
    base = a.results / "benchmarks" / "dense-variants" / name
    sets = a.dataset or ["synthetic"]
    if not check_run_datasets(ap, cfg, a.results, sets, "prepared"):
        return 2
    if not claim_variant_folder(base, {"dense": params}):
        return 2
    for ds in sets:
        data = dataset_root(ds, cfg["datasets"][ds], str(a.results))
        run, out = a.results / ds, base / ds
        out.mkdir(parents=True, exist_ok=True)
        stems = sorted(p.name[:-len(".meta.json")] for p in (run / "prepared").glob("*.meta.json"))
        jobs = [(str(run / "prepared" / f"{s}.png"), str(run / "prepared" / f"{s}.meta.json"),
                 str(out / f"{s}.json"), params)
                for s in stems if not (out / f"{s}.json").exists()]
        t0 = time.time()
        for stem, status, _ in sorted(run_jobs(_one, jobs, a.workers)):
            if status != "ok":
                print(f"{ds}/{stem}: {status}", file=sys.stderr)
        if jobs:
            print(f"{ds}: {len(jobs)} images in {time.time() - t0:.0f} s")
        folders = {name: out}
        if (run / "dense").is_dir():
            folders = {"run's dense source": run / "dense", name: out}
        print_side_by_side(data, folders, ds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
