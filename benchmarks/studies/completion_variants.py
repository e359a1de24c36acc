"""The scene step with other row / grid completion settings on a finished run, scored
beside the run's own scene step.

Re-runs the pipeline's scene step (:func:`rescu.pipeline.scene`: completion, VPs,
translation symmetry, counts) on every image of one dataset of a finished run, from its
prepared images and the scene step's input (``<results>/<dataset>/<scene.source>/``),
with the config's ``scene.completion`` keys overridden by ``--set KEY=VALUE`` (values
read as YAML; checked by :class:`rescu.completion.CompletionParams`). The results go to
``<out>/<image>.json`` (default ``<results>/benchmarks/completion-variants/<name>/``,
beside a ``params.json`` of the settings; a folder made with other settings is refused,
an image already there is not recomputed; rectified views are not kept). Then prints,
for the run's ``scene/`` and the variant on the same images: matched GT RPs, exact-count
rate and count MAE (:func:`rescu.evaluation.count_table.counting_table`), the instances completion
added, and where the dataset has the truth, translation symmetry at the config's
tolerance (TPR on equally spaced GT rows, FPR on the others; :func:`rescu.evaluation.ts_sweep`)
and the image VP's success at 5 degrees (:func:`rescu.evaluation.vp_frame`). Asserts
nothing.

Unlike ``snakemake --config 'scene={completion: {...}}'``, which reruns the same steps
but overwrites the run's results, this keeps both side by side.

Usage (after a run, from the repository root)::

    python benchmarks/studies/completion_variants.py results --set max_step_ratio=2.0
    python benchmarks/studies/completion_variants.py results/holdout --set end_instances=2 --workers 2
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def _one(job: tuple[str, str, str, str, dict[str, Any]]) -> tuple[str, str]:
    """The scene step of one image (rectified views to a temporary folder); (stem, status).
    Runs in a worker; a failing image gets the pipeline's empty result."""
    png, meta, src, out_json, scene = job
    from rescu import pipeline

    pipeline.limit_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        fail = pipeline.scene(png, meta, src, out_json, str(Path(tmp) / "rectified"), scene)
    return Path(out_json).stem, "ok" if fail is None else f"failed: {fail.message}"


def scores(data: Path, preds: dict[str, Path], images: list[str], ts_t: float
           ) -> list[dict[str, Any]]:
    """One row per method: counting, completion, TS and VP figures on ``images``."""
    from rescu.evaluation.count_table import counting_table
    from rescu.evaluation.core import load_predictions
    from rescu.evaluation.ts import ts_frame, ts_sweep
    from rescu.evaluation.vpd import vp_frame

    ct = counting_table(data, preds, images=images).set_index("method")
    have_truth = (data / "truth.json").exists()
    ts = (ts_sweep(ts_frame(data, preds, images=images), [ts_t]).set_index("method")
          if have_truth else None)
    vp = (vp_frame(data, preds, images=images)
          if (data / "vanishing_points.json").exists() else None)
    rows = []
    for m, d in preds.items():
        res = load_predictions(d, images)
        added = sum(int(p.extra.get("completed", 0)) for r in res.values() if r is not None
                    for p in r.patterns)
        r: dict[str, Any] = {"method": m, "images": len(images),
                             "matched_gt_rps": int(ct.loc[m, "n_matched"]),
                             "exact_rate": ct.loc[m, "exact_rate"],
                             "count_mae": ct.loc[m, "count_mae"], "completed": added}
        if ts is not None:
            r.update(ts_tpr=ts.loc[m, "tpr"], ts_fpr=ts.loc[m, "fpr"])
        if vp is not None and len(vp):
            e = vp[vp["method"] == m]["angle_error_deg"]
            r.update(vp_images=len(e), vp_at_5deg=float((e <= 5).mean()))
        rows.append(r)
    return rows


def main(argv: list[str] | None = None) -> int:
    import pandas as pd
    from _cli import (claim_variant_folder, images_with, parse_sets, run_dataset, run_jobs,
                      run_parser)

    from rescu.scene.completion import CompletionParams

    ap = run_parser(__doc__)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scene.completion key (repeatable; value read as YAML)")
    ap.add_argument("--name", default=None, help="variant name (default: from the --set items)")
    ap.add_argument("--out", type=Path, default=None, help="folder of the variant's JSONs")
    ap.add_argument("--workers", type=int, default=1, help="images computed in parallel")
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error(f"--workers must be at least 1, got {a.workers}")
    cfg, data = run_dataset(ap, a)
    try:
        over = parse_sets(a.sets)
        completion = {**(cfg["scene"].get("completion") or {}), **over}
        CompletionParams.from_dict(completion)
    except ValueError as e:
        ap.error(str(e))
    scene = {**cfg["scene"], "completion": completion}
    name = a.name or ("_".join(f"{k}={v}" for k, v in over.items()) or "config")
    out = a.out or a.results / "benchmarks" / "completion-variants" / name
    run = a.results / a.dataset
    src = run / cfg["scene"]["source"]
    for d in (run / "prepared", src, run / "scene", data / "annotations.json"):
        if not d.exists():
            print(f"{d}: not found (run the pipeline first)", file=sys.stderr)
            return 2
    if not claim_variant_folder(out, {"dataset": a.dataset, "scene": scene}):
        return 2
    stems = sorted(p.stem for p in src.glob("*.json")
                   if (run / "prepared" / f"{p.stem}.png").exists())
    jobs = [(str(run / "prepared" / f"{s}.png"), str(run / "prepared" / f"{s}.meta.json"),
             str(src / f"{s}.json"), str(out / f"{s}.json"), scene)
            for s in stems if not (out / f"{s}.json").exists()]
    t0 = time.time()
    done = run_jobs(_one, jobs, a.workers)
    for stem, status in sorted(done):
        if status != "ok":
            print(f"{stem}: {status}", file=sys.stderr)
    if jobs:
        print(f"{name}: {len(jobs)} images in {time.time() - t0:.0f} s; results in {out}")
    images = images_with(data, out, run / "scene")
    if not images:
        print("no image with results of both")
        return 0
    rows = scores(data, {"run": run / "scene", name: out}, images,
                  float(cfg["scene"]["symmetry"]["threshold"]))
    with pd.option_context("display.width", 250):
        print(pd.DataFrame(rows).round(3).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
