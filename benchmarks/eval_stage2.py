"""Instance recall/precision of RESCU-II against its stage-I input (IOD, h = 0.5).

Stage-I input is either read from per-image JSONs (``--stage1-dir``, files named
``<image stem>.json``), computed live with rescu.stage1 (``--run-stage1``), or simulated
from the ground truth (``--simulate-drop 0.4``: each GT RP loses that fraction of its
instances, at least 2 kept, and the kept boxes are jittered by ``--jitter`` of their
size). Prints one table row per image and the mean before/after (rescu.metrics).

Usage::

    python benchmarks/eval_stage2.py ../shared/data/chess --simulate-drop 0.4 --max-images 10
    python benchmarks/eval_stage2.py ../shared/data/chess --stage1-dir results/chess/rescu-i
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def simulate_stage1(name: str, w: int, h: int, gt_rps, drop: float, jitter: float,
                    rng: np.random.Generator):
    from rescu.types import ImageResult, Instance, Pattern

    pats = []
    for k, rp in enumerate(gt_rps):
        boxes = np.asarray(rp.boxes, float)
        n = len(boxes)
        n_keep = max(2, int(round(n * (1.0 - drop))))
        keep = np.sort(rng.choice(n, size=min(n, n_keep), replace=False))
        insts = []
        for b in boxes[keep]:
            x, y, bw, bh = b
            dx, dy = rng.uniform(-jitter, jitter, 2) * (bw, bh)
            sw, sh = np.exp(rng.uniform(-jitter, jitter, 2))
            nw, nh = bw * sw, bh * sh
            insts.append(Instance((float(x + bw / 2 + dx - nw / 2), float(y + bh / 2 + dy - nh / 2),
                                   float(nw), float(nh))))
        pats.append(Pattern(id=k, score=1.0, instances=insts))
    return ImageResult(name, w, h, "simulated-stage1", pats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("dataset", help="folder with images/ and annotations.json")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--stage1-dir", help="per-image stage-I JSONs (<stem>.json)")
    src.add_argument("--simulate-drop", type=float, help="fraction of GT instances dropped")
    src.add_argument("--run-stage1", action="store_true", help="run rescu.stage1 live")
    ap.add_argument("--jitter", type=float, default=0.05, help="box jitter of simulated stage I")
    ap.add_argument("--max-images", type=int, default=0, help="0 = all")
    ap.add_argument("--max-side", type=int, default=1024, help="processed image size")
    ap.add_argument("--params", default="{}", help="JSON dict of Stage2Params overrides")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0, help="simulation seed")
    ap.add_argument("--json-out", help="write per-image scores here")
    a = ap.parse_args(argv)

    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    import torch

    torch.set_num_threads(a.threads)
    from rescu import io
    from rescu.scene.counting import count_errors, count_pairs
    from rescu.evaluation.metrics import score_image, summarise
    from rescu.extension.stage2 import (Stage2Params, compute_stage2_features, predict_stage2,
                                        train_heads)

    params = Stage2Params.from_dict(json.loads(a.params))
    root = Path(a.dataset)
    gt = io.load_coco_rps(root / "annotations.json")
    names = sorted(n for n, rps in gt.items() if rps)
    if a.stage1_dir:
        names = [n for n in names if (Path(a.stage1_dir) / (Path(n).stem + ".json")).exists()]
    hard: dict[str, bool] = {}
    if (root / "truth.json").exists():       # synthetic benchmark: occluded/blurred scenes
        for rec in json.loads((root / "truth.json").read_text())["images"]:
            hard[rec["file_name"]] = bool(rec.get("hard", False))
    if a.max_images:
        names = names[: a.max_images]
    rng = np.random.default_rng(a.seed)
    before, after, rows = [], [], []
    counts1: list = []
    counts2: list = []
    hard_c1: list = []
    hard_c2: list = []
    hard_b: list = []
    hard_a: list = []
    easy_b: list = []
    easy_a: list = []
    t_all = time.perf_counter()
    print(f"{'image':40s} {'gt':>4s} {'s1':>4s} {'add':>4s}  {'P1':>5s} {'R1':>5s}  "
          f"{'P2':>5s} {'R2':>5s}  {'sec':>5s}")
    for name in names:
        im = io.load_image(root / name, max_side=a.max_side)
        w, h = im.original_size
        gt_boxes = [rp.boxes for rp in gt[name]]
        if a.simulate_drop is not None:
            s1 = simulate_stage1(name, w, h, gt[name], a.simulate_drop, a.jitter, rng)
        elif a.stage1_dir:
            p = Path(a.stage1_dir) / (Path(name).stem + ".json")
            if not p.exists():
                print(f"{name}: no stage-I JSON at {p}, skipped", file=sys.stderr)
                continue
            s1 = io.read_result(p)
        else:
            from rescu.discovery.features import extract_features
            from rescu.discovery.stage1 import discover, rps_to_patterns
            from rescu.types import ImageResult

            f = extract_features(im.rgb, None, im.scale_factor)
            s1 = ImageResult(name, w, h, "rescu-i", rps_to_patterns(f, discover(f).rps))
        t0 = time.perf_counter()
        feats = compute_stage2_features(im.rgb, im.scale_factor, s1, params)
        ckpt, info = train_heads(feats, s1, params)
        s2 = predict_stage2(feats, ckpt, s1, params)
        dt = time.perf_counter() - t0
        det1 = [[i.bbox for i in p.instances] for p in s1.patterns]
        det2 = [[i.bbox for i in p.instances] for p in s2.patterns]
        sc1, sc2 = score_image(det1, gt_boxes), score_image(det2, gt_boxes)
        before.append(sc1)
        after.append(sc2)
        gtc = [len(g) for g in gt_boxes]
        c1 = count_pairs([len(d) for d in det1], gtc, sc1.rp_assignment)
        c2 = count_pairs([len(d) for d in det2], gtc, sc2.rp_assignment)
        counts1.extend(c1)
        counts2.extend(c2)
        if hard.get(name, False):
            hard_c1.extend(c1)
            hard_c2.extend(c2)
        added = s2.extra.get("stage2", {}).get("added", 0)
        rows.append({"image": name, "before": sc1.as_dict(), "after": sc2.as_dict(),
                     "added": added, "seconds": dt, "hard": hard.get(name, False)})
        if name in hard:
            (hard_b if hard[name] else easy_b).append(sc1)
            (hard_a if hard[name] else easy_a).append(sc2)
        print(f"{name[-40:]:40s} {sc1.n_gt_instances:4d} {sc1.n_det_instances:4d} {added:4d}  "
              f"{sc1.instance_precision:5.3f} {sc1.instance_recall:5.3f}  "
              f"{sc2.instance_precision:5.3f} {sc2.instance_recall:5.3f}  {dt:5.1f}", flush=True)
    s_b, s_a = summarise(before), summarise(after)
    print(f"\n{root.name}: {len(before)} images, stage II total {time.perf_counter() - t_all:.1f} s")
    for m in ("instance_precision", "instance_recall", "rp_precision", "rp_recall"):
        print(f"  {m:20s} stage I {s_b[m + '_mean']:.3f}  stage II {s_a[m + '_mean']:.3f}  "
              f"delta {s_a[m + '_mean'] - s_b[m + '_mean']:+.3f}  (n={s_a[m + '_n']})")
    e1, e2 = count_errors(counts1), count_errors(counts2)
    print(f"  {'count_exact_rate':20s} stage I {e1['count_exact_rate']:.3f}  stage II "
          f"{e2['count_exact_rate']:.3f}  (matched RPs {e1['n_pairs']}, {e2['n_pairs']})")
    if hard_c1:
        h1, h2 = count_errors(hard_c1), count_errors(hard_c2)
        print(f"  [hard] count_exact_rate {h1['count_exact_rate']:.3f} -> {h2['count_exact_rate']:.3f}")
    for label, b_, a_ in (("hard", hard_b, hard_a), ("not hard", easy_b, easy_a)):
        if b_:
            sb, sa = summarise(b_), summarise(a_)
            print(f"  [{label}: {len(b_)} images] instance P {sb['instance_precision_mean']:.3f}"
                  f" -> {sa['instance_precision_mean']:.3f}  R {sb['instance_recall_mean']:.3f}"
                  f" -> {sa['instance_recall_mean']:.3f}")
    secs = [r["seconds"] for r in rows]
    if secs:
        print(f"  stage II seconds per image: mean {np.mean(secs):.1f}  max {np.max(secs):.1f}")
    if a.json_out:
        Path(a.json_out).write_text(json.dumps({"rows": rows, "before": s_b, "after": s_a,
                                                "count_before": e1, "count_after": e2},
                                               indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
