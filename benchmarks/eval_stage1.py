"""Evaluate stage I (RESCU-I or the GRASP baseline) on COCO-annotated datasets.

Usage::

    python benchmarks/eval_stage1.py ../shared/data/chess ../shared/data/cmp_facade \
        --method rescu-i --max-images 20 --max-side 1600 [--set key=value ...] \
        [--feat-set upsample_below=700 ...]

Prints, per dataset, the mean +- std (and number of images with a defined value) of
instance precision / recall and RP precision / recall (IOD h = 0.5, rescu.metrics),
and the mean seconds per image (features + discovery).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rescu.features import FeatureParams, extract_features  # noqa: E402
from rescu.grasp import GraspParams, discover_grasp  # noqa: E402
from rescu.io import load_coco_rps, load_image  # noqa: E402
from rescu.metrics import METRICS, score_image, summarise  # noqa: E402
from rescu.stage1 import Stage1Params, discover, rps_to_patterns  # noqa: E402


def _parse_set(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        out[k] = json.loads(v)
    return out


def evaluate(folder: Path, method: str, max_images: int, max_side: int, overrides: dict,
             feat_params: FeatureParams, verbose: bool = False) -> dict:
    gt = load_coco_rps(folder / "annotations.json")
    names = sorted(gt)[:max_images] if max_images > 0 else sorted(gt)
    scores, secs = [], []
    for name in names:
        img = load_image(folder / name, max_side=max_side)
        t0 = time.perf_counter()
        feats = extract_features(img.rgb, feat_params, img.scale_factor)
        if method == "rescu-i":
            out = discover(feats, Stage1Params.from_dict(overrides))
        else:
            out = discover_grasp(feats, GraspParams.from_dict(overrides))
        secs.append(time.perf_counter() - t0)
        pats = rps_to_patterns(feats, out.rps)
        s = score_image([[i.bbox for i in p.instances] for p in pats],
                        [rp.boxes for rp in gt[name]])
        scores.append(s)
        if verbose:
            print(f"  {name}: K={len(feats)} rps={[p.count for p in pats]} "
                  f"gt={[len(r.boxes) for r in gt[name]]} ip={s.instance_precision:.2f} "
                  f"ir={s.instance_recall:.2f} rp={s.rp_precision:.2f} rr={s.rp_recall:.2f} "
                  f"{secs[-1]:.2f}s chosen={out.chosen}", flush=True)
    summ = summarise(scores)
    summ["seconds_mean"] = float(np.mean(secs)) if secs else float("nan")
    return summ


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", type=Path)
    ap.add_argument("--method", choices=["rescu-i", "grasp"], default="rescu-i")
    ap.add_argument("--max-images", type=int, default=0, help="0 = all")
    ap.add_argument("--max-side", type=int, default=1600)
    ap.add_argument("--n-features", type=int, default=FeatureParams().n_features)
    ap.add_argument("--set", nargs="*", default=[], help="param overrides key=JSON")
    ap.add_argument("--feat-set", nargs="*", default=[],
                    help="FeatureParams overrides key=JSON (e.g. upsample_below=0)")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    overrides = _parse_set(a.set)
    fp = FeatureParams.from_dict({"n_features": a.n_features, **_parse_set(a.feat_set)})
    print(f"method={a.method} max_side={a.max_side} n_features={a.n_features} "
          f"overrides={overrides} features={fp}")
    hdr = f"{'dataset':<14}{'n':>4}" + "".join(f"{m:>24}" for m in METRICS) + f"{'s/img':>8}"
    rows = []
    for ds in a.datasets:
        s = evaluate(ds, a.method, a.max_images, a.max_side, overrides, fp, a.verbose)
        row = f"{ds.name:<14}{s['n_images']:>4}" + "".join(
            f"{s[m + '_mean']:>10.3f} +- {s[m + '_std']:.3f}({s[m + '_n']:>2})" for m in METRICS)
        rows.append(row + f"{s['seconds_mean']:>8.2f}")
    print(hdr)
    for r in rows:
        print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
