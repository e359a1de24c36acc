"""How good could the dense source's RPs be with a perfect choice among its candidates?

For every image of a dataset of a finished run, re-computes the dense source's feature
map on the prepared picture (``<results>/<dataset>/prepared/``) and all its candidate
groups of recurring blobs (:func:`rescu.extension.dense.dense_candidates`: before the
plane-tiling test and the ``max_patterns`` cut), and scores each group's instance
precision against its best ground-truth RP
(:func:`_diagnostics.rp_precisions`; "good" = 0.5 or more, what the
paper's RP metric accepts). Then prints, per dataset, the paper's instance precision /
recall (mean over images, undefined values left out, as in the RP table) of

* ``pipeline``: the dense source as the step selects (the ``max_patterns`` best-scored
  groups that do not tile the plane; the score includes the objectness when
  ``objectness_crops`` > 0), which is the RP table's *Dense source* row;
* ``oracle, best one``: per image the one group of highest precision;
* ``oracle, good, max_patterns``: the ``max_patterns`` best-scored good groups;
* ``oracle, every good``: every good group;
* ``every candidate``: all groups, those that tile the plane too. Its recall is the
  ceiling of any selection among today's candidates (its precision means nothing);
* with ``--with METHOD``, ``every candidate + METHOD``: the same plus the run's RPs of
  that method (``<results>/<dataset>/<METHOD>/<image>.json``, e.g. ``rescu-ii``): the
  recall that a perfect choice among everything the run and the source found reaches;
  and ``every good + good of METHOD``: every good group and every good RP of the
  method (a perfect choice of whole RPs from both, no instance removed);

the number of candidates and good ones per image, and the ROC AUC of the ranking score
between good and other groups (those that pass the tiling test). The oracle rows are
ceilings of a better selection with today's candidates; the gap between them and 1.0 is
what candidate generation (blobs and grouping) loses. Per-candidate rows go to
``<results>/benchmarks/dense-oracle/<dataset>.tsv``. Asserts nothing.

Usage (after a run with the datasets, from the repository root)::

    python benchmarks/studies/dense_oracle.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars --dataset chess [--set min_similarity=0.5]

One to two seconds per image (one backbone pass, two threads) plus the backbone's load.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

from _cli import parse_sets  # noqa: E402


def _auc(good: Any, score: Any) -> float:
    """ROC AUC of ``score`` for ``good``; NaN without both classes."""
    import numpy as np
    from sklearn.metrics import roc_auc_score

    good = np.asarray(good, bool)
    return float(roc_auc_score(good, score)) if 0 < good.sum() < len(good) else float("nan")


def main(argv: list[str] | None = None) -> int:
    import numpy as np
    import pandas as pd

    from _cli import check_run_datasets, variants_parser

    from rescu import pipeline
    from rescu.config import load_config
    from rescu.data.datasets import dataset_root
    from rescu.evaluation.core import write_tsv
    from _diagnostics import rp_precisions
    from rescu.evaluation.metrics import score_image
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.dense import (DenseParams, dense_candidates, dense_map, objectness_for,
                                       rank_candidates)
    from rescu.io import InputError, load_coco_rps
    from rescu.params import deep_merge

    from rescu import io

    ap = variants_parser(__doc__)
    ap.add_argument("--with", dest="with_method", default=None, metavar="METHOD",
                    help="also every candidate plus the run's RPs of METHOD (e.g. rescu-ii)")
    a = ap.parse_args(argv)
    cfg = load_config(a.config, stage2=False)
    try:
        params = DenseParams.from_dict(deep_merge(cfg["dense"], parse_sets(a.sets)))
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    sets = a.dataset or ["synthetic"]
    if not check_run_datasets(ap, cfg, a.results, sets, "prepared"):
        return 2
    pipeline.limit_threads(2, torch=True)
    backbone = FrozenBackbone(params.backbone, feature_stride=16)
    out_dir = a.results / "benchmarks" / "dense-oracle"
    out_dir.mkdir(parents=True, exist_ok=True)
    for ds in sets:
        data = dataset_root(ds, cfg["datasets"][ds], str(a.results))
        gt = load_coco_rps(data / "annotations.json")
        rows, scores = [], {k: [] for k in ("pipeline", "oracle, best one",
                                            "oracle, good, max_patterns",
                                            "oracle, every good", "every candidate")}
        both = f"every candidate + {a.with_method}"
        good_both = f"every good + good of {a.with_method}"
        if a.with_method:
            scores[both], scores[good_both] = [], []
        for f, gts in gt.items():
            stem = Path(f).stem
            png = a.results / ds / "prepared" / f"{stem}.png"
            meta = a.results / ds / "prepared" / f"{stem}.meta.json"
            if not png.is_file():
                print(f"{ds}/{stem}: no prepared image, skipped", file=sys.stderr)
                continue
            try:
                rgb, m = pipeline.read_prepared(str(png), str(meta))
                if m.get("failure"):
                    raise InputError(f"{meta}: the run could not prepare this image")
                fmap, s = dense_map(rgb, params, backbone)
            except (InputError, ValueError) as e:
                print(f"{ds}/{stem}: skipped ({e})", file=sys.stderr)
                continue
            # the step's ranking: groups that tile the plane are never selected, so only
            # the others get their objectness (dense.objectness_crops)
            cands = dense_candidates(fmap, 8.0, params)
            cands = rank_candidates([c for c in cands if c.touching <= params.max_touching],
                                    objectness_for(rgb, s, params, backbone)) + \
                [c for c in cands if c.touching > params.max_touching]
            to_orig = 1.0 / (s * float(m["scale_factor"]))
            boxes = [(c.boxes * to_orig).tolist() for c in cands]
            truth = [g.boxes for g in gts]
            prec = rp_precisions(boxes, truth)
            flat = [k for k, c in enumerate(cands) if c.touching <= params.max_touching]
            good = [k for k in flat if prec[k] >= 0.5]
            picks = {"pipeline": flat[:params.max_patterns],
                     "oracle, best one": [int(np.argmax(prec))] if len(cands) else [],
                     "oracle, good, max_patterns": good[:params.max_patterns],
                     "oracle, every good": good, "every candidate": list(range(len(cands)))}
            for name, ks in picks.items():
                sc = score_image([boxes[k] for k in ks], truth)
                scores[name].append((sc.instance_precision, sc.instance_recall))
            if a.with_method:
                res = a.results / ds / a.with_method / f"{stem}.json"
                own = ([[ins.bbox for ins in p.instances] for p in io.read_result(res).patterns]
                       if res.is_file() else None)
                if own is None:
                    print(f"{ds}/{stem}: no {a.with_method} result, counted as none",
                          file=sys.stderr)
                sc = score_image(boxes + (own or []), truth)
                scores[both].append((sc.instance_precision, sc.instance_recall))
                mine = [r for r, q in zip(own or [], rp_precisions(own or [], truth)) if q >= 0.5]
                sc = score_image([boxes[k] for k in good] + mine, truth)
                scores[good_both].append((sc.instance_precision, sc.instance_recall))
            rows += [{"image": f, "rank": k, "n": len(c.boxes), "score": c.score,
                      "touching": c.touching, "precision": prec[k],
                      "selected": k in picks["pipeline"]} for k, c in enumerate(cands)]
        df = pd.DataFrame(rows, columns=["image", "rank", "n", "score", "touching",
                                         "precision", "selected"])
        write_tsv(df, out_dir / f"{ds}.tsv")
        n_img = len(scores["pipeline"])
        flat_df = df[df.touching <= params.max_touching]
        print(f"## {ds}: {n_img} images, {len(df) / max(n_img, 1):.1f} candidate groups "
              f"per image, {(flat_df.precision >= 0.5).sum() / max(n_img, 1):.1f} good; "
              f"AUC of the score (good vs other) "
              f"{_auc(flat_df.precision >= 0.5, flat_df.score):.2f}")
        print("| selection | inst. P | inst. R | images with a selection |")
        print("|---|---:|---:|---:|")
        for name, v in scores.items():
            arr = np.array(v, float).reshape(-1, 2)
            print(f"| {name} | {np.nanmean(arr[:, 0]):.3f} | {np.nanmean(arr[:, 1]):.3f} | "
                  f"{int((~np.isnan(arr[:, 0])).sum())} |")
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
