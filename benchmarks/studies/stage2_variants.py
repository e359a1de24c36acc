"""RESCU-II with other stage-II settings on a finished run, scored beside RESCU-I and the
run's own RESCU-II.

Re-runs the three stage-II steps of the pipeline (:func:`rescu.pipeline.stage2_features`,
``stage2_train``, ``stage2_predict``; features and head in a temporary folder) on every
image of one dataset of a finished run, from its prepared images
(``<results>/<dataset>/prepared/``) and stage-I results (``rescu-i/``), with the config's
``stage2`` keys overridden by ``--set SECTION.KEY=VALUE`` (a key of a ``stage2`` section,
``predict.merge.enabled`` one level deeper; values read as YAML; each override is checked
by :class:`rescu.extension.params.Stage2Params`). The results go to
``<out>/<image>.json`` (default ``<results>/benchmarks/stage2-variants/<name>/``, beside
a ``params.json`` of the settings; a folder made with other settings is refused, an
image already there is not recomputed). Then prints the mean per-image instance and RP
precision / recall at IOD 0.5 of RESCU-I, the run's RESCU-II and the variant, on the
images all three have, in the tables' format (:func:`rescu.evaluation.summary_markdown`;
synthetic data also per subset and hard / not hard), and the paired Wilcoxon p-value of
the variant against the run's RESCU-II (:func:`rescu.evaluation.significance_table`).
Asserts nothing.

When every ``--set`` key is in the ``predict`` section (the keys that act only in
prediction: the gates, ``visible_half*``, ``merge``), the run's own features and head
(``<results>/<dataset>/stage2/``) are reused and only prediction is re-run (seconds per
image); otherwise all three steps are.

What comes after stage II (scene, completion) is not re-run: compare with the run's
``rescu-ii/`` (as the RP discovery table does), not with ``final/``.

Usage (after a run, from the repository root)::

    python benchmarks/studies/stage2_variants.py results --set examples.occlude_prob=0.5
    python benchmarks/studies/stage2_variants.py results/holdout-11 --set examples.occlude_prob=0.5
    python benchmarks/studies/stage2_variants.py results --set predict.visible_half=true
    python benchmarks/studies/stage2_variants.py results --name ft --set backbone.finetune=true \\
        --set backbone.device=cuda --workers 6   # end-to-end fine-tuning, on a GPU
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

from _cli import parse_sets  # noqa: E402  (re-exported: the tests call it from here)


def nested(over: dict[str, Any]) -> dict[str, Any]:
    """``{"a.b": v}`` -> ``{"a": {"b": v}}`` (the ``--set`` keys as a nested override)."""
    out: dict[str, Any] = {}
    for key, value in over.items():
        node = out
        *path, last = key.split(".")
        for k in path:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {key}: {k!r} is set to a value and is a section")
        node[last] = value
    return out


def _one(job: tuple[str, str, str, str, dict[str, Any], dict[str, int],
                    tuple[str, str] | None, tuple[str | None, dict[str, Any] | None]]
         ) -> tuple[str, str, float, int | None]:
    """Stage II of one image through the pipeline's own three steps (features and head in
    a temporary folder), or only its prediction step from ``reuse`` = (the run's
    features HDF5, head checkpoint); ``threads`` is the config's ``threads`` section
    (each step with its rule's thread count); returns (stem, status, seconds, fine-tuning
    epochs or None). ``dense`` = (the dense step's map file, the ``dense`` section), both
    None without the dense source: RESCU-II keeps one box per object as the pipeline's
    step does. Runs in a worker; a failing image gets the pipeline's empty result."""
    png, meta, s1_json, out_json, params, threads, reuse, dense = job
    t = time.time()
    stem = Path(out_json).stem
    from rescu import pipeline

    epochs = None
    if reuse is not None:
        pipeline.limit_threads(threads["stage2_head"], torch=True)
        fail = pipeline.stage2_predict(reuse[0], reuse[1], s1_json, out_json, meta, params,
                                       *dense)
    else:
        fail, epochs = _all_steps(png, meta, s1_json, out_json, params, threads, dense)
    status = "ok" if fail is None else f"failed in {fail.get('stage')}: {fail.get('message')}"
    return stem, status, time.time() - t, epochs


def _all_steps(png: str, meta: str, s1_json: str, out_json: str, params: dict[str, Any],
               threads: dict[str, int], dense: tuple[str | None, dict[str, Any] | None]
               ) -> tuple[dict[str, Any] | None, int | None]:
    """The pipeline's three stage-II steps, features and head in a temporary folder, each
    with its rule's thread count (``threads``: the config's ``threads`` section); returns
    (the failure record or None, fine-tuning epochs or None)."""
    from rescu import io, pipeline

    def head(step: Any, *args: Any) -> dict[str, Any] | None:
        pipeline.limit_threads(threads["stage2_head"], torch=True)
        return step(*args)

    with tempfile.TemporaryDirectory() as tmp:
        h5, ckpt = str(Path(tmp) / "feats.h5"), str(Path(tmp) / "head.h5")
        pipeline.limit_threads(threads["stage2_features"], torch=True)
        fail = (pipeline.stage2_features(png, meta, s1_json, h5, params)
                or head(pipeline.stage2_train, h5, s1_json, ckpt, params)
                or head(pipeline.stage2_predict, h5, ckpt, s1_json, out_json, meta, params,
                        *dense))
        epochs = None
        if params.get("finetune") and fail is None:
            from rescu.extension.proposal_features import finetune_record

            feats, _ = io.read_h5(h5)
            epochs = (finetune_record(feats) or {}).get("epochs")
    return fail, epochs


def main(argv: list[str] | None = None) -> int:
    from _cli import claim_variant_folder, images_with, run_dataset, run_jobs, run_parser

    from rescu.evaluation.core import (evaluate_rp_dataset, frame_markdown, significance_table,
                                       summary_markdown, summary_table)
    from rescu.extension.params import PREDICT_SECTION, Stage2Params
    from rescu.params import deep_merge as merged

    ap = run_parser(__doc__)
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    metavar="SECTION.KEY=VALUE",
                    help="override a key of a stage2 section, e.g. examples.occlude_prob=0.5 "
                         "(repeatable; value read as YAML)")
    ap.add_argument("--name", default=None, help="variant name (default: from the --set items)")
    ap.add_argument("--out", type=Path, default=None, help="folder of the variant's JSONs")
    ap.add_argument("--workers", type=int, default=1, help="images computed in parallel")
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads of every step (default: the config's `threads`, as the "
                         "pipeline's stage-II rules: "
                         "float sums depend on it)")
    a = ap.parse_args(argv)
    if a.threads is not None and a.threads < 1:
        ap.error(f"--threads must be at least 1, got {a.threads}")
    cfg, data = run_dataset(ap, a)
    try:
        over = parse_sets(a.sets)
        params = merged(cfg["stage2"], nested(over))
        p = Stage2Params.from_dict(params)
    except ValueError as e:
        ap.error(str(e))
    name = a.name or ("_".join(f"{k}={v}" for k, v in over.items()) or "config")
    out = a.out or a.results / "benchmarks" / "stage2-variants" / name
    run = a.results / a.dataset
    for d in (run / "prepared", run / "rescu-i", run / "rescu-ii", data / "annotations.json"):
        if not d.exists():
            print(f"{d}: not found (run the pipeline first)", file=sys.stderr)
            return 2
    if not claim_variant_folder(out, {"dataset": a.dataset, "stage2": params}):
        return 2
    stems = sorted(p.stem for p in (run / "rescu-i").glob("*.json")
                   if (run / "prepared" / f"{p.stem}.png").exists())
    # prediction-only overrides: the run's own features and head, where it has them
    predict_only = bool(over) and all(k.split(".")[0] == PREDICT_SECTION for k in over)

    def reuse(s: str) -> tuple[str, str] | None:
        h5, pt = run / "stage2" / f"{s}.feats.h5", run / "stage2" / f"{s}.head.h5"
        return (str(h5), str(pt)) if predict_only and h5.exists() and pt.exists() else None

    threads = {k: cfg["threads"][k] if a.threads is None else a.threads
               for k in ("stage2_features", "stage2_head")}
    def dense(s: str) -> tuple[str | None, dict[str, Any] | None]:
        m = run / "dense" / f"{s}.map.h5"
        return (str(m), cfg["dense"]) if cfg["dense"]["enabled"] and m.exists() else (None, None)

    jobs = [(str(run / "prepared" / f"{s}.png"), str(run / "prepared" / f"{s}.meta.json"),
             str(run / "rescu-i" / f"{s}.json"), str(out / f"{s}.json"), params, threads,
             reuse(s), dense(s))
            for s in stems if not (out / f"{s}.json").exists()]
    if jobs and predict_only:
        n = sum(j[-1] is not None for j in jobs)
        print(f"prediction-only keys: {n} of {len(jobs)} images from the run's own features "
              f"and head")
    t0 = time.time()
    done = run_jobs(_one, jobs, a.workers)
    for stem, status, _, _ in sorted(done):
        if status != "ok":
            print(f"{stem}: {status}", file=sys.stderr)
    if jobs:
        sec = [s for _, st, s, _ in done if st == "ok"]
        print(f"{name}: {len(sec)} of {len(jobs)} images computed in {time.time() - t0:.0f} s "
              f"(per image: median {np.median(sec) if sec else float('nan'):.1f} s, "
              f"{a.workers} worker(s)); results in {out}")
        ep = [e for _, _, _, e in done if e is not None]
        if ep:
            print(f"fine-tuned backbone on {len(ep)} images: epochs median {np.median(ep):.0f}, "
                  f"{sum(e >= p.head.max_epochs for e in ep)} stopped at max_epochs "
                  f"({p.head.max_epochs})")
    images = images_with(data, out, run / "rescu-ii")
    if not images:
        print("no image with results of all three methods")
        return 0
    df = evaluate_rp_dataset(data, {"RESCU-I": run / "rescu-i", "RESCU-II": run / "rescu-ii",
                                    name: out}, images=images)
    print("\n" + summary_markdown(summary_table(df), decimals=3))
    sig = significance_table(df)
    sig = sig[(sig.method_a == "RESCU-II") & (sig.method_b == name)]
    print(f"Paired Wilcoxon p, {name} against the run's RESCU-II:\n")
    print(frame_markdown(sig[["subset", "metric", "n_pairs", "mean_a", "mean_b", "p_value"]],
                         decimals=3))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
