"""Evaluate stage I (RESCU-I or the GRASP baseline) on COCO-annotated datasets.

Usage::

    python benchmarks/eval_stage1.py ../shared/data/chess ../shared/data/cmp_facade \
        --method rescu-i --max-images 20 --max-side 1600 [--set key=value ...] \
        [--feat-set upsample_below=700 ...]

Prints, per dataset, the mean +- std (and number of images with a defined value) of
instance precision / recall and RP precision / recall (IOD h = 0.5, rescu.metrics),
the exact-count rate of matched RPs (rescu.counting.count_pairs on
score_image(...).rp_assignment, pooled over the images' pairs; also on the "hard"
subset when the folder has a truth.json, as the synthetic benchmark does), and the mean
seconds per image (features + discovery). ``--feat-cache DIR`` keeps the extracted
features between runs (pickles keyed by dataset, image and feature parameters).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rescu.scene.counting import count_errors, count_pairs  # noqa: E402
from rescu.discovery.features import FeatureParams, extract_features  # noqa: E402
from rescu.discovery.grasp import GraspParams, discover_grasp  # noqa: E402
from rescu.io import load_coco_rps, load_image  # noqa: E402
from rescu.evaluation.metrics import METRICS, score_image, summarise  # noqa: E402
from rescu.discovery.stage1 import Stage1Params, discover, rps_to_patterns  # noqa: E402


def _parse_set(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        out[k] = json.loads(v)
    return out


def evaluate(folder: Path, method: str, max_images: int, max_side: int, overrides: dict,
             feat_params: FeatureParams, verbose: bool = False,
             feat_cache: Path | None = None) -> dict:
    gt = load_coco_rps(folder / "annotations.json")
    names = sorted(gt)[:max_images] if max_images > 0 else sorted(gt)
    hard: dict[str, bool] = {}
    if (folder / "truth.json").exists():
        truth = json.loads((folder / "truth.json").read_text())
        hard = {im["file_name"]: bool(im.get("hard", False)) for im in truth["images"]}
    scores, secs = [], []
    pairs_all: list[tuple[int, int]] = []
    pairs_hard: list[tuple[int, int]] = []
    for name in names:
        t0 = time.perf_counter()
        cpath = None
        if feat_cache is not None:
            key = hashlib.sha1(f"{folder.resolve()}|{name}|{max_side}|{feat_params}"
                               .encode()).hexdigest()[:16]
            cpath = feat_cache / f"{key}.pkl"
        if cpath is not None and cpath.exists():
            feats = pickle.loads(cpath.read_bytes())
        else:
            img = load_image(folder / name, max_side=max_side)
            t0 = time.perf_counter()
            feats = extract_features(img.rgb, feat_params, img.scale_factor)
            if cpath is not None:
                cpath.parent.mkdir(parents=True, exist_ok=True)
                cpath.write_bytes(pickle.dumps(feats))
        if method == "rescu-i":
            out = discover(feats, Stage1Params.from_dict(overrides))
        else:
            out = discover_grasp(feats, GraspParams.from_dict(overrides))
        secs.append(time.perf_counter() - t0)
        pats = rps_to_patterns(feats, out.rps)
        s = score_image([[i.bbox for i in p.instances] for p in pats],
                        [rp.boxes for rp in gt[name]])
        scores.append(s)
        cp = count_pairs([p.count for p in pats], [len(r.boxes) for r in gt[name]],
                         s.rp_assignment)
        pairs_all += cp
        if hard.get(name, False):
            pairs_hard += cp
        if verbose:
            print(f"  {name}: K={len(feats)} rps={[p.count for p in pats]} "
                  f"gt={[len(r.boxes) for r in gt[name]]} ip={s.instance_precision:.2f} "
                  f"ir={s.instance_recall:.2f} rp={s.rp_precision:.2f} rr={s.rp_recall:.2f} "
                  f"{secs[-1]:.2f}s chosen={out.chosen} count_pairs={cp}"
                  f"{' hard' if hard.get(name, False) else ''}", flush=True)
    summ = summarise(scores)
    ce, ch = count_errors(pairs_all), count_errors(pairs_hard)
    summ["count_exact"], summ["count_n"] = ce["count_exact_rate"], ce["n_pairs"]
    summ["count_exact_hard"], summ["count_n_hard"] = ch["count_exact_rate"], ch["n_pairs"]
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
    ap.add_argument("--feat-cache", type=Path, default=None,
                    help="folder caching extracted features between runs")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    overrides = _parse_set(a.set)
    fp = FeatureParams.from_dict({"n_features": a.n_features, **_parse_set(a.feat_set)})
    print(f"method={a.method} max_side={a.max_side} n_features={a.n_features} "
          f"overrides={overrides} features={fp}")
    hdr = f"{'dataset':<14}{'n':>4}" + "".join(f"{m:>24}" for m in METRICS) + f"{'s/img':>8}" \
        + f"{'exact(n)':>12}{'exact_hard(n)':>15}"
    rows = []
    for ds in a.datasets:
        s = evaluate(ds, a.method, a.max_images, a.max_side, overrides, fp, a.verbose, a.feat_cache)
        row = f"{ds.name:<14}{s['n_images']:>4}" + "".join(
            f"{s[m + '_mean']:>10.3f} +- {s[m + '_std']:.3f}({s[m + '_n']:>2})" for m in METRICS)
        rows.append(row + f"{s['seconds_mean']:>8.2f}"
                    + f"{s['count_exact']:>8.3f}({s['count_n']:>2})"
                    + f"{s['count_exact_hard']:>11.3f}({s['count_n_hard']:>2})")
    print(hdr)
    for r in rows:
        print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
