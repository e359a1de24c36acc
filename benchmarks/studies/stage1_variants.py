"""RESCU-I with other stage-I settings on a finished run, scored beside the run's own
RESCU-I on every image of one or more datasets.

Re-runs the pipeline's stage-I step (:func:`rescu.pipeline.stage1`) on each image's
cached features (``<results>/<dataset>/features/<image>.h5``) with the config's
``stage1`` keys overridden by ``--set KEY=VALUE`` and its ``dense`` keys by ``--set
dense.KEY=VALUE`` (values read as YAML, checked by
:class:`rescu.discovery.stage1.Stage1Params` and
:class:`rescu.discovery.sources.DenseParams`). With ``dense.enabled`` (the default) it
takes the run's dense step as the pipeline does (``<dataset>/dense/<image>.json`` and
its map, not recomputed): the RESCU-I of the run, so keys that RESCU-I alone reads
(``dense.min_confidence``, ``dense.confidence_stage1_score_scale``, stage I's) can be
varied in minutes; keys of the dense step itself need the pipeline. Results go to
``<results>/benchmarks/stage1-variants/<name>/<dataset>/<image>.json`` beside a
``params.json`` of the settings (a folder made with other settings is refused; an image
already there is not recomputed). Then prints, per dataset, the mean ± std over images
of the paper's instance precision / recall, the RP precision / recall and the any-RP
instance figures (:mod:`rescu.evaluation.metrics`) of the run's RESCU-I and the variant,
and the paired Wilcoxon p-value of each metric; last, the mean over the datasets of the
any-RP instance F1 (of the mean precision and recall) of both. Asserts nothing.

Stage I takes about a second per image, so a variant over every image of the real sets
(``make realdev`` first) takes a few minutes on 2 workers. Stage II is not re-run: for
RESCU-II figures, run the pipeline with the setting.

Usage (from the repository root)::

    make realdev
    python benchmarks/studies/stage1_variants.py results/realdev \\
        --dataset cmp_facade --dataset spb_facades --set max_patterns=8 --workers 2
    python benchmarks/studies/stage1_variants.py results/realdev --dataset chess \\
        --set dense.confidence_stage1_score_scale=0.02 --workers 2
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

from _cli import f1, parse_sets  # noqa: E402


def _one(job: tuple[str, str, str, dict[str, Any], dict[str, Any] | None]
         ) -> tuple[str, str, float]:
    """RESCU-I of one image (pipeline step, one thread; with ``dense`` params, the run's
    dense step's result and map); (stem, status, seconds)."""
    h5, meta, out_json, params, dense = job
    t = time.time()
    from rescu import pipeline

    pipeline.limit_threads(1)
    out_h5 = str(Path(out_json).with_suffix(".rps.h5"))
    png = meta.replace(".meta.json", ".png")
    found = {}
    if dense is not None:
        stem = Path(meta).name[:-len(".meta.json")]
        d = Path(meta).parents[1] / "dense"
        found = {"dense_json": str(d / f"{stem}.json"), "dense_params": dense,
                 "dense_map_h5": str(d / f"{stem}.map.h5")}
    fail = pipeline.stage1(h5, meta, out_json, out_h5, params, png=png, **found)
    Path(out_h5).unlink(missing_ok=True)
    status = "ok" if fail is None else f"failed: {fail.get('message')}"
    return Path(out_json).stem, status, time.time() - t


def main(argv: list[str] | None = None) -> int:
    from _cli import claim_variant_folder, print_side_by_side, run_jobs, variants_parser

    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.discovery.sources import DenseParams
    from rescu.discovery.stage1 import Stage1Params
    from rescu.params import deep_merge

    ap = variants_parser(__doc__)
    a = ap.parse_args(argv)
    cfg = load_config(a.config)
    try:
        over = parse_sets(a.sets)
        params = deep_merge(cfg["stage1"], {k: v for k, v in over.items()
                                            if not k.startswith("dense.")})
        Stage1Params.from_dict(params)
        dense = deep_merge(cfg["dense"], {k[len("dense."):]: v for k, v in over.items()
                                          if k.startswith("dense.")})
        DenseParams.from_dict(dense)
        if not dense.get("enabled"):
            dense = None
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    name = a.name or ("_".join(f"{k}={v}" for k, v in over.items()) or "config")
    base = a.results / "benchmarks" / "stage1-variants" / name
    sets = a.dataset or ["synthetic"]
    f1s: dict[str, list[float]] = {}
    for ds in sets:
        if ds not in cfg["datasets"]:
            ap.error(f"dataset {ds!r} is not in the config")
        need = ["features", "rescu-i"] + (["dense"] if dense is not None else [])
        for d in (a.results / ds / n for n in need):
            if not d.is_dir():
                print(f"{d}: not found (run the pipeline first)", file=sys.stderr)
                return 2
    if not claim_variant_folder(base, {"stage1": params, "dense": dense}):
        return 2
    for ds in sets:
        data = dataset_root(ds, cfg["datasets"][ds], str(a.results))
        run, out = a.results / ds, base / ds
        out.mkdir(parents=True, exist_ok=True)
        stems = sorted(p.stem for p in (run / "rescu-i").glob("*.json"))
        jobs = [(str(run / "features" / f"{s}.h5"), str(run / "prepared" / f"{s}.meta.json"),
                 str(out / f"{s}.json"), params, dense)
                for s in stems if not (out / f"{s}.json").exists()]
        t0 = time.time()
        for stem, status, _ in sorted(run_jobs(_one, jobs, a.workers)):
            if status != "ok":
                print(f"{ds}/{stem}: {status}", file=sys.stderr)
        if jobs:
            print(f"{ds}: {len(jobs)} images in {time.time() - t0:.0f} s")
        print_side_by_side(data, {"RESCU-I": run / "rescu-i", name: out}, ds)
        for label, folder in (("RESCU-I", run / "rescu-i"), (name, out)):
            f1s.setdefault(label, []).append(_any_f1(data, folder))
    print("\nmean any-RP instance F1 over the datasets (F1 of each set's mean P and R):")
    for label, v in f1s.items():
        print(f"  {label}: {np.mean(v):.3f}")
    return 0


def _any_f1(data: Path, folder: Path) -> float:
    """F1 of the mean any-RP instance precision and recall over the images of ``data``
    with a result in ``folder``."""
    from rescu.evaluation.metrics import score_image
    from rescu.io import load_coco_rps, read_result

    truth = {Path(k).stem: [r.boxes for r in v]
             for k, v in load_coco_rps(data / "annotations.json").items()}
    pr = []
    for js in sorted(folder.glob("*.json")):
        if js.stem in truth:
            s = score_image([[i.bbox for i in p.instances] for p in read_result(js).patterns],
                            truth[js.stem])
            pr.append((s.instance_precision_any, s.instance_recall_any))
    if not pr:
        return float("nan")
    p, r = np.nanmean(np.array(pr, float), 0)
    return f1(p, r)


if __name__ == "__main__":
    raise SystemExit(main())
