""""Count these": one (or three) ground-truth boxes as examples, every instance found.

For every image of each dataset (COCO-style ``annotations.json``, as in
``../shared/data``), the counted class is the image's ``count_class`` (else its largest
ground-truth RP); the example is its box of median area (``--k 3``: the three boxes
nearest the median area). :func:`rescu.extension.prompted.find_like` runs on the photo
as :func:`rescu.discover` prepares it (longer side at most ``image.max_side``) and its
boxes (the examples included) are matched one-to-one to the class's boxes (IOD > 0.5, as
the RP metrics). Prints per dataset and pooled: coverage (matched / ground truth),
precision (matched / found), mean and median relative count error ``|n - n_gt| / n_gt``,
the share of photos counted within 10 % and 20 %, and seconds per photo (backbone
included, one thread per process as set by the caller's environment).

``--save FILE`` keeps every image's candidates (all peaks before the threshold, with
scores), the examples' reference score and the ground truth, for
``benchmarks/studies/count_threshold.py``.

Usage (from the repository root)::

    python benchmarks/count_these.py                      # the 8 box sets of ../shared/data
    python benchmarks/count_these.py --k 3
    python benchmarks/count_these.py --data ../shared/data --set blood_cells --set nuclei
    python benchmarks/count_these.py --param min_score=0.5 --save /tmp/cands.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1])]

BOX_SETS = ["blood_cells", "nuclei", "aquarium", "parking_lot", "aerial_cars", "chess",
            "cmp_facade", "spb_facades"]


def counted_boxes(images: dict, rps: list, file_name: str) -> np.ndarray:
    """The boxes (n, 4) of what is counted in one image: its ``count_class``, else its
    largest ground-truth RP."""
    cls = images.get(file_name, {}).get("count_class")
    pick = [r for r in rps if r.category == cls] if cls else []
    rp = pick[0] if pick else max(rps, key=lambda r: len(r.boxes))
    return np.asarray(rp.boxes, np.float64).reshape(-1, 4)


def example_boxes(gt: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` boxes of ``gt`` whose areas are nearest the median area (ties: first)."""
    area = gt[:, 2] * gt[:, 3]
    order = np.argsort(np.abs(area - np.median(area)), kind="stable")
    return gt[order[:k]]


def evaluate(rows: list[dict]) -> dict:
    """Pooled figures of per-image rows (n_gt, n_found, n_matched, seconds)."""
    n_gt = sum(r["n_gt"] for r in rows)
    n_found = sum(r["n_found"] for r in rows)
    n_match = sum(r["n_matched"] for r in rows)
    err = np.array([abs(r["n_found"] - r["n_gt"]) / r["n_gt"] for r in rows])
    return {"images": len(rows), "coverage": n_match / max(n_gt, 1),
            "precision": n_match / max(n_found, 1),
            "mean_err": float(err.mean()) if len(err) else float("nan"),
            "median_err": float(np.median(err)) if len(err) else float("nan"),
            "within10": float((err <= 0.10 + 1e-9).mean()) if len(err) else float("nan"),
            "within20": float((err <= 0.20 + 1e-9).mean()) if len(err) else float("nan"),
            "s_per_photo": float(np.mean([r["seconds"] for r in rows])) if rows else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--set", dest="sets", action="append", default=None,
                    help=f"dataset folder under --data (repeatable; default {BOX_SETS})")
    ap.add_argument("--k", type=int, default=1, help="examples per photo")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                    help="override a key of the config's prompt section")
    ap.add_argument("--save", type=Path, default=None, help="candidates of every image (JSON)")
    ap.add_argument("--max-images", type=int, default=None, help="first N images of each set")
    a = ap.parse_args(argv)

    import yaml

    from rescu.config import load_config
    from rescu.evaluation.metrics import match_boxes
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.prompted import PromptParams, check_examples, find_like
    from rescu.io import load_coco_rps, load_image

    cfg = load_config(None)
    prompt = dict(cfg["prompt"])
    for kv in a.param:
        key, _, val = kv.partition("=")
        if key not in prompt:
            ap.error(f"--param {kv}: {key!r} is not a key of the prompt section")
        prompt[key] = yaml.safe_load(val)
    params = PromptParams.from_dict(prompt)
    max_side = int(cfg["image"]["max_side"])
    backbone = FrozenBackbone("efficientnet-lite0")
    sets = a.sets or BOX_SETS
    saved, all_rows, table = {}, [], []
    for name in sets:
        root = a.data / name
        ann = root / "annotations.json"
        if not ann.is_file():
            print(f"{name}: no {ann}, skipped", file=sys.stderr)
            continue
        gts = load_coco_rps(ann)
        images = {im["file_name"]: im for im in json.loads(ann.read_text())["images"]}
        rows = []
        for fn in list(gts)[:a.max_images]:
            if not gts[fn]:
                continue
            gt = counted_boxes(images, gts[fn], fn)
            if len(gt) < 2:
                continue
            img = load_image(root / fn, max_side=max_side)
            rgb, s = img.rgb, img.scale_factor
            gts_s = gt * s
            ex = check_examples(example_boxes(gts_s, a.k), rgb.shape[1], rgb.shape[0], 1.0)
            t0 = time.perf_counter()
            f = find_like(rgb, ex, backbone, params)
            dt = time.perf_counter() - t0
            m = match_boxes(f.boxes, gts_s, 0.5)
            rows.append({"n_gt": len(gt), "n_found": f.count, "n_matched": len(m),
                         "seconds": dt})
            if a.save:
                saved[f"{name}/{fn}"] = {
                    "gt": gts_s.round(2).tolist(), "examples": ex.round(2).tolist(),
                    "candidates": f.candidates.round(2).tolist(),
                    "scores": np.round(f.candidate_scores, 4).tolist(),
                    "reference": round(f.reference, 4),
                    "background": round(f.background, 4)}
        r = evaluate(rows)
        table.append((name, r))
        all_rows += rows
        print(_line(name, r), flush=True)
    if len(table) > 1:
        print(_line("ALL (pooled)", evaluate(all_rows)))
        mean = {k: float(np.mean([r[k] for _, r in table])) for k in table[0][1]}
        print(_line("mean of sets", mean))
    if a.save:
        a.save.write_text(json.dumps(saved))
    return 0


def _line(name: str, r: dict) -> str:
    return (f"{name:14s} images {r['images']:4.0f}  coverage {r['coverage']:.3f}  precision "
            f"{r['precision']:.3f}  count error mean {r['mean_err']:.3f} median "
            f"{r['median_err']:.3f}  within 10% {r['within10']:.2f} 20% {r['within20']:.2f}  "
            f"{r['s_per_photo']:.2f} s/photo")


if __name__ == "__main__":
    raise SystemExit(main())
