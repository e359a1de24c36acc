"""Whole objects (rescu.extension.objects) on a finished run, every image of each dataset,
at several confidence thresholds: the figures of docs/studies/whole-objects.md.

For each image of the run's ``<dataset>/prepared/`` folder: the dense step with whole
objects (:func:`rescu.extension.dense.find_dense`, the config's ``dense`` section with
``--set`` overrides), combined in mode ``objects`` with the run's own stage-I RPs
(``<dataset>/rescu-i/<image>.json``, which must come from a run *without* the dense
source: stage I's RPs alone), every RP scored (:func:`rescu.extension.objects.score_patterns`),
then split at each ``--threshold`` (:func:`rescu.discovery.sources.split_by_confidence`).
That is what RESCU-I does per image with the default config (before stage II).

Prints, per dataset and threshold, the mean over every image of the any-RP instance
precision / recall, the paper's instance and RP precision / recall, and the mean
relative count error of the dominant RP (:func:`rescu.scene.counting.dominant_pattern`,
the most confident) against the largest GT RP; then the
mean any-RP F1 over the datasets per threshold (how ``dense.min_confidence`` was
chosen). Rows ``stage I`` (the run's RPs as they are) and ``dense`` (the whole-object RPs
alone, no threshold) are printed for comparison. Asserts nothing.

Usage (from the repository root; a run of stage I alone over the full sets)::

    snakemake --cores 2 --configfile config/realdev.yaml \\
        --config results_dir=results/stage1 "dense={enabled: false}" -- <the rescu-i JSONs>
    python benchmarks/studies/whole_objects.py results/stage1 --dataset chess \\
        --dataset aerial_cars --dataset spb_facades --dataset cmp_facade
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

from _cli import f1, parse_sets  # noqa: E402

THRESHOLDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def _image(png: Path, meta: Path, s1_json: Path, params: Any, backbone: Any
           ) -> tuple[list[Any], list[Any], list[Any]]:
    """Stage I's RPs, the dense whole-object RPs, and both combined and scored (original
    pixels) for one image."""
    from rescu import io, pipeline
    from rescu.discovery.sources import combine_sources
    from rescu.extension.dense import dense_levels, find_dense
    from rescu.extension.objects import score_patterns

    rgb, m = pipeline.read_prepared(str(png), str(meta))
    sf = float(m["scale_factor"])
    sparse = io.read_result(s1_json).patterns
    levels = dense_levels(rgb, params, backbone)
    dense = find_dense(rgb, params, backbone, scale_factor=sf, levels=levels)
    both = combine_sources(copy.deepcopy(sparse), copy.deepcopy(dense), params)
    score_patterns(rgb, both, sf, params, *levels[0])
    return sparse, dense, both


def main(argv: list[str] | None = None) -> int:
    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.discovery.sources import DenseParams, split_by_confidence
    from rescu.evaluation.metrics import score_image
    from rescu.extension.backbone import FrozenBackbone
    from rescu.io import load_coco_rps
    from rescu.scene.counting import dominant_pattern
    from rescu.params import deep_merge
    from rescu.types import ImageResult

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="the run's results folder")
    ap.add_argument("--dataset", action="append", required=True)
    ap.add_argument("--config", default=None, help="the run's config file (datasets)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a dense key for this study, e.g. --set extent=false")
    ap.add_argument("--threshold", action="append", type=float, default=None)
    a = ap.parse_args(argv)
    cfg = load_config(a.config, stage2=False)
    dense_cfg = deep_merge(cfg["dense"], parse_sets(a.set))
    params = DenseParams.from_dict({**dense_cfg, "mode": "objects"})
    thresholds = tuple(a.threshold or THRESHOLDS)
    backbone = FrozenBackbone(params.backbone, feature_stride=16)
    f1s: dict[float, list[float]] = {t: [] for t in thresholds}
    for ds in a.dataset:
        data = dataset_root(ds, cfg["datasets"][ds], str(a.results))
        truth = {Path(k).stem: [r.boxes for r in v]
                 for k, v in load_coco_rps(data / "annotations.json").items()}
        rows: dict[str, list[tuple[float, ...]]] = {}
        for png in sorted((a.results / ds / "prepared").glob("*.png")):
            stem = png.stem
            s1 = a.results / ds / "rescu-i" / f"{stem}.json"
            if stem not in truth or not s1.is_file():
                continue
            sparse, dense, both = _image(png, png.with_suffix(".meta.json"), s1, params,
                                         backbone)
            variants = {"stage I": sparse, "dense": dense}
            for t in thresholds:
                res = ImageResult(image=stem, width=0, height=0, method="x",
                                  patterns=copy.deepcopy(both))
                split_by_confidence(res, t, params)
                variants[f"objects >= {t:g}"] = res.patterns
            gt = truth[stem]
            big = max((len(g) for g in gt), default=0)
            for name, pats in variants.items():
                s = score_image([[i.bbox for i in p.instances] for p in pats], gt)
                k = dominant_pattern(pats)
                dom = 0 if k is None else len(pats[k].instances)
                rows.setdefault(name, []).append(
                    (s.instance_precision_any, s.instance_recall_any, s.instance_precision,
                     s.instance_recall, s.rp_precision, s.rp_recall,
                     abs(dom - big) / max(big, 1)))
        print(f"\n{ds} ({len(rows.get('stage I', []))} images): any-RP P / R, paper's "
              "instance P / R, RP P / R, count error of the dominant RP")
        for name, r in rows.items():
            m = np.nanmean(np.array(r, float), 0)
            print(f"  {name:<16} {m[0]:.3f} / {m[1]:.3f}   {m[2]:.3f} / {m[3]:.3f}   "
                  f"{m[4]:.3f} / {m[5]:.3f}   {m[6]:.2f}")
            if name.startswith("objects >= "):
                f1s[float(name.split(">= ")[1])].append(f1(m[0], m[1]))
    print("\nmean any-RP F1 over the datasets, per threshold:")
    for t in thresholds:
        print(f"  {t:g}: {np.mean(f1s[t]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
