"""Sweep of stage II's lattice-window gates on the artefacts of a finished run.

RESCU-II keeps a lattice window (a window where the RP's instance lattice predicts a
missing instance) when the head's class probability is at least
``stage2.lattice_score_threshold`` and its feature lies within
``stage2.lattice_distance_ratio`` x the RP radius of a DBSCAN centre. Both act in
prediction only, so this script re-runs :func:`rescu.stage2.predict_stage2` on the
stage-II features and heads a run left under ``<results>/<dataset>/stage2/`` for each
pair of values (nothing is retrained), optionally the scene step (row and grid
completion) after it, and prints, per dataset and setting, the instance precision and
recall (mean over images, IOD h = 0.5; ``hard_*`` over the synthetic scenes marked
hard) and the exact-count rate per matched GT RP, beside RESCU-I.

Usage (after ``snakemake --cores 2``)::

    python benchmarks/studies/sweep_lattice_gates.py results --datasets synthetic cmp_facade \\
        --ratios 1.0 1.25 1.5 --thresholds 0.99 0.97 0.95 0.9 --scene

The dataset folders are read from the configuration (``config/config.yaml`` merged over
the defaults; synthetic:
``<results>/data/synthetic``; relative paths from the current folder, as snakemake
reads them: run it from the repository root).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's rescu package


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from rescu import io, pipeline
    from rescu.extension.params import Stage2Params
    from rescu.extension.predict import predict_stage2
    from rescu.extension.train import load_checkpoint
    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.evaluation.count_table import count_frame
    from rescu.evaluation.core import evaluate_rp_dataset

    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--datasets", nargs="+", default=["synthetic"])
    ap.add_argument("--ratios", nargs="+", type=float, default=[1.0, 1.25, 1.5])
    ap.add_argument("--thresholds", nargs="+", type=float, default=[0.99, 0.97, 0.95, 0.9])
    ap.add_argument("--scene", action="store_true",
                    help="also run the scene step (completion) and count on its output")
    ap.add_argument("--config", type=Path,
                    default=Path(__file__).resolve().parents[2] / "config" / "config.yaml")
    a = ap.parse_args(argv)
    cfg = load_config(a.config)
    pd.set_option("display.width", 200)
    for name in a.datasets:
        root = a.results / name
        stems = sorted(p.stem for p in (root / "rescu-i").glob("*.json"))
        stems = [s for s in stems if (root / "stage2" / f"{s}.head.h5").is_file()]
        if not stems:
            print(f"{name}: no stage-II artefacts under {root}", file=sys.stderr)
            continue
        dd = dataset_root(name, cfg["datasets"][name], str(a.results))
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            preds = {"RESCU-I": root / "rescu-i"}
            for r, t in itertools.product(a.ratios, a.thresholds):
                P = Stage2Params.variant(cfg["stage2"], {"predict": {
                    "lattice_distance_ratio": r, "lattice_score_threshold": t}})
                out = Path(tmp) / f"{r}_{t}"
                (out / "ii").mkdir(parents=True)
                (out / "scene").mkdir()
                for s in stems:
                    feats, _ = io.read_h5(root / "stage2" / f"{s}.feats.h5")
                    ckpt = load_checkpoint(root / "stage2" / f"{s}.head.h5")
                    res = predict_stage2(feats, ckpt["head"],
                                         io.read_result(root / "rescu-i" / f"{s}.json"), P)
                    res.method = "rescu-ii"
                    io.write_json(out / "ii" / f"{s}.json", res)
                    if a.scene:
                        pipeline.scene(str(root / "prepared" / f"{s}.png"),
                                       str(root / "prepared" / f"{s}.meta.json"),
                                       str(out / "ii" / f"{s}.json"),
                                       str(out / "scene" / f"{s}.json"),
                                       str(Path(tmp) / "rect" / s), cfg["scene"])
                preds[f"ratio={r} thr={t}"] = out / ("scene" if a.scene else "ii")
            images = [io.read_result(root / "rescu-i" / f"{s}.json").image for s in stems]
            sf = evaluate_rp_dataset(dd, preds, images=images)
            cf = count_frame(dd, preds, images=images)
            for m, g in sf.groupby("method", sort=False):
                c = cf[(cf["method"] == m) & (cf["gt_rp"] >= 0) & cf["counted"]]
                h = g[g["hard"] == True]  # noqa: E712  (NaN on real datasets)
                rows.append({"dataset": name, "method": m, "images": len(g),
                             "inst_P": g["instance_precision"].mean(),
                             "inst_R": g["instance_recall"].mean(),
                             "hard_P": h["instance_precision"].mean() if len(h) else float("nan"),
                             "hard_R": h["instance_recall"].mean() if len(h) else float("nan"),
                             "exact_count": c["exact"].mean() if len(c) else float("nan")})
        print(pd.DataFrame(rows).round(4).to_string(index=False))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
