"""Evaluate scene understanding: VP errors, translation symmetry, counts, runtime.

Modes (all print figures; nothing is asserted)::

    # synthetic benchmark: GT boxes + truth.json rows, feature points from the GT
    # instance corners/centres with --noise px Gaussian noise (a stand-in for stage I)
    python benchmarks/eval_scene.py synth --n 24 --out /tmp/synth_scene
    python benchmarks/eval_scene.py synth --dataset /tmp/synth_scene   # already generated

    # explicit-line baseline (LSD + RANSAC) on York Urban, true focal length
    python benchmarks/eval_scene.py york --data ../shared/data/york_urban

    # per-image prediction JSONs (rescu.io.read_result) against a dataset folder that has
    # vanishing_points.json and/or annotations.json (and optionally truth.json);
    # --analyse re-runs analyse_scene on them first; with several --pred folders the
    # first is compared with each other by a paired Wilcoxon test on VP errors
    python benchmarks/eval_scene.py pred --pred out/york/rescu-i --data ../shared/data/york_urban --analyse

VP errors are the vector-based error (degrees) to the closest ground-truth VP, with the
true focal length / principal point when the dataset gives them, else
f = (W + H) / 4 and the image centre; a missing VP counts as a failure (infinite error).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rescu.scene import counting as C  # noqa: E402
from rescu import io  # noqa: E402
from rescu import layout as L  # noqa: E402
from rescu.scene import analyse as SC  # noqa: E402
from rescu.scene import symmetry as S  # noqa: E402
from rescu.scene.vp.errors import closest_gt_error, success_rate, vector_error  # noqa: E402
from rescu.evaluation.vpd import paired_test  # noqa: E402
from rescu.scene.vp.lsd import line_vanishing_point  # noqa: E402
from rescu.evaluation.metrics import score_image  # noqa: E402
from rescu.types import ImageResult, Instance, Pattern  # noqa: E402

THRESHOLDS = (1.0, 2.0, 5.0, 10.0)


def _vp_summary(name: str, errors: list[float]) -> None:
    e = np.asarray(errors, float)
    if len(e) == 0:
        print(f"{name}: no images")
        return
    sr = success_rate(e, THRESHOLDS)
    fin = e[np.isfinite(e)]
    med = float(np.median(np.where(np.isnan(e), np.inf, e)))
    print(f"{name}: n={len(e)} median_err_deg={med:.3f} "
          f"mean_finite_err_deg={fin.mean() if len(fin) else float('nan'):.3f} "
          f"missing={int((~np.isfinite(e)).sum())} "
          + " ".join(f"success@{t:g}deg={s:.3f}" for t, s in zip(THRESHOLDS, sr)))


# ----------------------------------------------------------------------------- synthetic
def _instance_points(inst: dict[str, Any]) -> np.ndarray:
    """Stand-in stage-I features of one GT instance (truth.json): its projected quad
    vertices and centre, (5, 2) pixels."""
    return np.concatenate([np.asarray(inst["quad"], float).reshape(4, 2),
                           np.asarray(inst["center"], float).reshape(1, 2)])


def gt_results(dataset: Path, noise: float, seed: int) -> tuple[list[ImageResult],
                                                                 list[dict[str, Any]]]:
    """ImageResults built from the ground truth of a synthetic dataset.

    One pattern per truth pattern; instances = its annotation boxes in row order (then
    any instance in no row); feature points = the instances' projected quad vertices and
    centres from truth.json + N(0, noise^2) px. Returns the results and the truth
    records (``truth.json`` images) in the same order.
    """
    coco = io.read_json(dataset / "annotations.json")
    truth = io.read_json(dataset / "truth.json")
    anns = {a["id"]: a for a in coco["annotations"]}
    rng = np.random.default_rng(seed)
    results = []
    for ti in truth["images"]:
        pats = []
        for k, tp in enumerate(ti["patterns"]):
            tinst = {i["id"]: i for i in tp["instances"]}
            ids = [a for row in tp["rows"] for a in row]
            ids = ids + sorted(set(tinst) - set(ids))
            insts = [Instance(tuple(float(v) for v in anns[a]["bbox"])) for a in ids]
            fp = np.stack([_instance_points(tinst[a]) for a in ids], axis=1)  # (M, N, 2)
            fp = fp + rng.normal(0.0, noise, fp.shape)
            pats.append(Pattern(id=k, score=1.0, instances=insts, feature_points=fp,
                                extra={"gt_ids": ids}))
        results.append(ImageResult(ti["file_name"], int(ti["width"]), int(ti["height"]),
                                   "gt-features", pats))
    return results, truth["images"]


def run_synth(args: argparse.Namespace) -> None:
    dataset = Path(args.dataset) if args.dataset else Path(args.out)
    if not args.dataset:
        from rescu.data import synth  # written by another helper

        t0 = time.perf_counter()
        synth.generate_dataset(dataset, synth.SynthParams.from_dict(
            {"n_images": args.n, "seed": args.seed}))
        print(f"generated {args.n} images in {time.perf_counter() - t0:.1f} s -> {dataset}")
    params = SC.SceneParams()
    results, truth = gt_results(dataset, args.noise, args.seed)
    vps = io.load_vanishing_points(dataset / "vanishing_points.json")
    dom_err, pat_err, times = [], [], []
    frontal_inf, frontal_n = 0, 0
    row_eq, row_uneq, pat_ts = [], [], []
    for res, ti in zip(results, truth):
        t0 = time.perf_counter()
        out = SC.analyse_scene(res, params)
        times.append(time.perf_counter() - t0)
        g = vps.get(ti["file_name"], {})
        gts = g.get("vanishing_points", [])
        size = (res.width, res.height)
        if ti.get("subset") == "projective" and gts:
            dom_err.append(np.inf if out.vanishing_point is None else closest_gt_error(
                out.vanishing_point.homogeneous, gts, "vector", size, g.get("focal_px"),
                g.get("principal_point")))
        for p, tp in zip(out.patterns, ti["patterns"]):
            if tp.get("vanishing_point") is not None:
                pat_err.append(np.inf if p.vanishing_point is None else vector_error(
                    p.vanishing_point.homogeneous, np.asarray(tp["vanishing_point"], float),
                    size, g.get("focal_px"), g.get("principal_point")))
            elif ti.get("subset") == "frontal":
                frontal_n += 1
                frontal_inf += int(p.vanishing_point is not None
                                   and p.vanishing_point.homogeneous[2] == 0.0)
            if p.translation_symmetry is not None:
                pat_ts.append((bool(tp.get("translation_symmetry", tp["equal_spacing"])),
                               p.translation_symmetry.detected))
            # per GT row, with the truth ordering
            pos = {a: i for i, a in enumerate(p.extra["gt_ids"])}
            centres, _ = L.instance_centres_sizes(np.array([i.bbox for i in p.instances]))
            for row in tp["rows"]:
                if len(row) < params.symmetry.min_instances:
                    continue
                ts = S.translation_symmetry(p.feature_points, centres,
                                            [np.array([pos[a] for a in row])],
                                            params.symmetry)
                (row_eq if tp["equal_spacing"] else row_uneq).append(bool(ts.detected))
    print(f"synthetic: {len(results)} images, noise {args.noise} px, "
          f"analyse_scene {1000 * np.mean(times):.1f} ms/image (mean)")
    _vp_summary("dominant VP (projective images, closest GT VP)", dom_err)
    _vp_summary("per-pattern VP (patterns with a GT VP)", pat_err)
    print(f"frontal patterns with VP at infinity (w == 0): {frontal_inf}/{frontal_n}")
    print(f"TS per GT row (truth order), t={params.symmetry.threshold}: "
          f"detected on equal rows {np.mean(row_eq) if row_eq else float('nan'):.3f} "
          f"(n={len(row_eq)}), false positives on unequal rows "
          f"{np.mean(row_uneq) if row_uneq else float('nan'):.3f} (n={len(row_uneq)})")
    if pat_ts:
        a = np.array(pat_ts)
        tp_ = a[a[:, 0]]
        fp_ = a[~a[:, 0]]
        print(f"TS per pattern (own rows): detected on TS patterns "
              f"{tp_[:, 1].mean() if len(tp_) else float('nan'):.3f} (n={len(tp_)}), "
              f"false positives {fp_[:, 1].mean() if len(fp_) else float('nan'):.3f} "
              f"(n={len(fp_)})")


# ----------------------------------------------------------------------------- York
def run_york(args: argparse.Namespace) -> None:
    data = Path(args.data)
    gt = io.load_vanishing_points(data / "vanishing_points.json")
    params = SC.SceneParams().vp
    errs, times = [], []
    names = sorted(gt)[: args.limit] if args.limit else sorted(gt)
    for name in names:
        g = gt[name]
        im = io.load_image(data / name)
        t0 = time.perf_counter()
        vp = line_vanishing_point(im.rgb, params, im.scale_factor)
        times.append(time.perf_counter() - t0)
        errs.append(np.inf if vp is None else closest_gt_error(
            vp.homogeneous, g["vanishing_points"], "vector", (g["width"], g["height"]),
            g["focal_px"], g["principal_point"]))
    _vp_summary(f"LSD baseline on {data.name} (true focal, closest GT VP)", errs)
    print(f"LSD baseline runtime: mean {1000 * np.mean(times):.1f} ms/image, "
          f"median {1000 * np.median(times):.1f} ms/image (image load excluded)")


# ----------------------------------------------------------------------------- predictions
def _eval_pred_dir(pred: Path, data: Path, analyse: bool) -> dict[str, Any]:
    params = SC.SceneParams()
    vps = (io.load_vanishing_points(data / "vanishing_points.json")
           if (data / "vanishing_points.json").exists() else None)
    rps = io.load_coco_rps(data / "annotations.json") \
        if (data / "annotations.json").exists() else None
    files = sorted(pred.glob("*.json"))
    errs: dict[str, float] = {}
    pairs: list[tuple[int, int]] = []
    for f in files:
        try:
            res = io.read_result(f)
        except io.InputError as e:
            print(f"skip {f}: {e}", file=sys.stderr)
            continue
        if analyse:
            res = SC.analyse_scene(res, params)
        if vps is not None and res.image in vps and vps[res.image]["vanishing_points"]:
            g = vps[res.image]  # images without a GT VP (frontal synthetic) are left out
            errs[res.image] = (np.inf if res.vanishing_point is None else closest_gt_error(
                res.vanishing_point.homogeneous, g["vanishing_points"], "vector",
                (g["width"], g["height"]), g["focal_px"], g["principal_point"]))
        if rps is not None and res.image in rps:
            gt = rps[res.image]
            s = score_image([[i.bbox for i in p.instances] for p in res.patterns],
                            [g_.boxes for g_ in gt])
            pairs += C.count_pairs([p.count for p in res.patterns],
                                   [len(g_.boxes) for g_ in gt], s.rp_assignment)
    return {"n_files": len(files), "vp_errors": errs, "count_pairs": pairs}


def run_pred(args: argparse.Namespace) -> None:
    data = Path(args.data)
    outs = []
    for d in args.pred:
        r = _eval_pred_dir(Path(d), data, args.analyse)
        outs.append(r)
        print(f"{d}: {r['n_files']} prediction files")
        if r["vp_errors"]:
            _vp_summary(f"  image VP vs {data.name}", list(r["vp_errors"].values()))
            if args.per_image:
                for k, e in sorted(r["vp_errors"].items(), key=lambda kv: -kv[1]):
                    print(f"    {k}: {e:.3f} deg")
        if r["count_pairs"]:
            ce = C.count_errors(r["count_pairs"])
            print("  counts on matched RPs: " + json.dumps(
                {k: round(v, 4) if isinstance(v, float) else v for k, v in ce.items()}))
    for d, r in zip(args.pred[1:], outs[1:]):
        common = sorted(set(outs[0]["vp_errors"]) & set(r["vp_errors"]))
        if common:
            p = paired_test([outs[0]["vp_errors"][k] for k in common],
                              [r["vp_errors"][k] for k in common])
            print(f"paired Wilcoxon {args.pred[0]} vs {d} on {len(common)} images: p={p:.4g}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("synth")
    a.add_argument("--n", type=int, default=24)
    a.add_argument("--out", default="/tmp/rescu_synth_scene")
    a.add_argument("--dataset", default=None, help="use an already generated dataset")
    a.add_argument("--noise", type=float, default=1.0, help="feature noise, pixels")
    a.add_argument("--seed", type=int, default=0)
    b = sub.add_parser("york")
    b.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared"
                                         / "data" / "york_urban"))
    b.add_argument("--limit", type=int, default=0)
    c = sub.add_parser("pred")
    c.add_argument("--pred", nargs="+", required=True)
    c.add_argument("--data", required=True)
    c.add_argument("--analyse", action="store_true")
    c.add_argument("--per-image", action="store_true",
                   help="print every image's VP error, worst first")
    args = ap.parse_args(argv)
    {"synth": run_synth, "york": run_york, "pred": run_pred}[args.mode](args)


if __name__ == "__main__":
    main()
