"""RESCU-I with other stage-I settings on a finished run, scored beside the run's own
RESCU-I on every image of one or more datasets.

Re-runs the pipeline's stage-I step (:func:`rescu.pipeline.stage1`) on each image's
cached features (``<results>/<dataset>/features/<image>.h5``) with the config's
``stage1`` keys overridden by ``--set KEY=VALUE`` (values read as YAML, checked by
:class:`rescu.discovery.stage1.Stage1Params`). Results go to
``<results>/benchmarks/stage1-variants/<name>/<dataset>/<image>.json`` beside a
``params.json`` of the settings (a folder made with other settings is refused; an image
already there is not recomputed). Then prints, per dataset, the mean ± std over images
of the paper's instance precision / recall, the RP precision / recall and the any-RP
instance figures (:mod:`rescu.evaluation.metrics`) of the run's RESCU-I and the variant,
and the paired Wilcoxon p-value of each metric. Asserts nothing.

Stage I takes about a second per image, so a variant over every image of the real sets
(``make realdev`` first) takes a few minutes on 2 workers. Stage II is not re-run: for
RESCU-II figures, run the pipeline with the setting.

Usage (from the repository root)::

    make realdev
    python benchmarks/studies/stage1_variants.py results/realdev \\
        --dataset cmp_facade --dataset spb_facades --set max_patterns=8 --workers 2
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
    """Stage I of one image (pipeline step, one thread); (stem, status, seconds)."""
    h5, meta, out_json, params = job
    t = time.time()
    from rescu import pipeline

    pipeline.limit_threads(1)
    out_h5 = str(Path(out_json).with_suffix(".rps.h5"))
    png = meta.replace(".meta.json", ".png")
    fail = pipeline.stage1(h5, meta, out_json, out_h5, params, png=png)
    Path(out_h5).unlink(missing_ok=True)
    status = "ok" if fail is None else f"failed: {fail.get('message')}"
    return Path(out_json).stem, status, time.time() - t


def main(argv: list[str] | None = None) -> int:
    from _cli import claim_variant_folder, print_side_by_side, run_jobs, variants_parser

    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.discovery.stage1 import Stage1Params
    from rescu.params import deep_merge

    ap = variants_parser(__doc__)
    a = ap.parse_args(argv)
    cfg = load_config(a.config)
    try:
        over = parse_sets(a.sets)
        params = deep_merge(cfg["stage1"], over)
        Stage1Params.from_dict(params)
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    name = a.name or ("_".join(f"{k}={v}" for k, v in over.items()) or "config")
    base = a.results / "benchmarks" / "stage1-variants" / name
    sets = a.dataset or ["synthetic"]
    for ds in sets:
        if ds not in cfg["datasets"]:
            ap.error(f"dataset {ds!r} is not in the config")
        for d in (a.results / ds / "features", a.results / ds / "rescu-i"):
            if not d.is_dir():
                print(f"{d}: not found (run the pipeline first)", file=sys.stderr)
                return 2
    if not claim_variant_folder(base, {"stage1": params}):
        return 2
    for ds in sets:
        data = dataset_root(ds, cfg["datasets"][ds], str(a.results))
        run, out = a.results / ds, base / ds
        out.mkdir(parents=True, exist_ok=True)
        stems = sorted(p.stem for p in (run / "rescu-i").glob("*.json"))
        jobs = [(str(run / "features" / f"{s}.h5"), str(run / "prepared" / f"{s}.meta.json"),
                 str(out / f"{s}.json"), params)
                for s in stems if not (out / f"{s}.json").exists()]
        t0 = time.time()
        for stem, status, _ in sorted(run_jobs(_one, jobs, a.workers)):
            if status != "ok":
                print(f"{ds}/{stem}: {status}", file=sys.stderr)
        if jobs:
            print(f"{ds}: {len(jobs)} images in {time.time() - t0:.0f} s")
        print_side_by_side(data, {"RESCU-I": run / "rescu-i", name: out}, ds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
