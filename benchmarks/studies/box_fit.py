"""Whether a run's RP instances fail for their box or for their place.

    python benchmarks/studies/box_fit.py RESULTS --dataset aerial_cars [--data ../shared/data]
        [--folder rescu-i] [--source dense] [--verbose]

For every image of one dataset of a finished run, every reported RP's instances
(``<RESULTS>/<dataset>/<folder>/<image>.json``, ``patterns``; with ``--verbose`` also the
``candidate_patterns`` below the confidence threshold, per RP) are compared with all the
image's ground-truth boxes (any category): how many pass IOD > 0.5 against some GT box
(what the metric counts), and how many fail it although their centre lies on a GT
object (a box of the wrong shape or size on a right place), and the median share of its
object that an instance with its centre on a GT object covers (its area over that of the
smallest GT box holding its centre: 1 for a box of the whole object, 0.25 for one of half
its width and height). ``--source dense`` (or ``stage1``) counts only the RPs of that
source. Prints the totals over the dataset. Asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

# the checkout's rescu package
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from rescu.boxes import iod_matrix  # noqa: E402


def _centre_on(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n, m) bool: the centre of ``det[i]`` strictly inside ``gt[j]`` (``[x, y, w, h]``)."""
    cx, cy = det[:, 0] + det[:, 2] / 2, det[:, 1] + det[:, 3] / 2
    return ((cx[:, None] > gt[:, 0]) & (cx[:, None] < gt[:, 0] + gt[:, 2])
            & (cy[:, None] > gt[:, 1]) & (cy[:, None] < gt[:, 1] + gt[:, 3]))


def fit(det: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) bool twice: IOD > 0.5 against some GT box; centre inside a GT box but not
    passing. ``det`` (n, 4), ``gt`` (m, 4), ``[x, y, w, h]``."""
    if not len(det) or not len(gt):
        return np.zeros(len(det), bool), np.zeros(len(det), bool)
    ok = iod_matrix(det, gt).max(1) > 0.5
    on = _centre_on(det, gt).any(1)
    return ok, on & ~ok


def area_share(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n,) float: each box's area over that of the smallest GT box holding its centre;
    NaN where none does. ``det`` (n, 4), ``gt`` (m, 4), ``[x, y, w, h]``.

    >>> area_share(np.array([[10., 10., 10., 10.], [90., 90., 4., 4.]]),
    ...            np.array([[0., 0., 40., 40.], [5., 5., 20., 20.]]))
    array([0.25,  nan])
    """
    out = np.full(len(det), np.nan)
    if not len(det) or not len(gt):
        return out
    area = np.where(_centre_on(det, gt), gt[:, 2] * gt[:, 3], np.inf).min(1)
    hit = np.isfinite(area)
    out[hit] = det[hit, 2] * det[hit, 3] / np.maximum(area[hit], 1e-9)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--folder", default="rescu-i", help="method folder of the run")
    ap.add_argument("--source", choices=("dense", "stage1"), default=None,
                    help="only the RPs of this source (default: all)")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    if not (a.data / a.dataset / "annotations.json").is_file():
        print(f"{a.data / a.dataset / 'annotations.json'}: not found", file=sys.stderr)
        return 2
    ann = json.loads((a.data / a.dataset / "annotations.json").read_text())
    stems = {i["id"]: Path(i["file_name"]).stem for i in ann["images"]}
    gt: dict[str, list] = collections.defaultdict(list)
    for x in ann["annotations"]:
        gt[stems[x["image_id"]]].append(x["bbox"])
    tot = collections.Counter()
    shares: list[np.ndarray] = []
    for stem in sorted(stems.values()):
        p = a.results / a.dataset / a.folder / f"{stem}.json"
        if not p.is_file():
            continue
        d = json.loads(p.read_text())
        g = np.array(gt.get(stem, []), float).reshape(-1, 4)
        tot["images"] += 1
        tot["gt"] += len(g)
        kinds = [("reported", d.get("patterns", []))]
        if a.verbose:
            kinds.append(("below", d.get("candidate_patterns", [])))
            print(f"{stem}: {len(g)} GT boxes")
        for kind, pats in kinds:
            for q in pats:
                if a.source and (q.get("source") or "stage1") != a.source:
                    continue
                b = np.array([i["bbox"] for i in q["instances"]], float).reshape(-1, 4)
                ok, wrong_box = fit(b, g)
                if kind == "reported":
                    tot["instances"] += len(b)
                    tot["pass"] += int(ok.sum())
                    tot["on_object_fail"] += int(wrong_box.sum())
                    shares.append(area_share(b, g))
                if a.verbose and len(b):
                    print(f"  {kind:8s} {q.get('source', 'stage1'):6s} n={len(b):3d} "
                          f"conf={q.get('confidence', float('nan')):.2f} "
                          f"box {np.median(b[:, 2]):.0f}x{np.median(b[:, 3]):.0f} "
                          f"pass {ok.mean():.2f} on-object-fail {wrong_box.mean():.2f}")
    print(f"{a.dataset}: {tot['images']} images, {tot['gt']} GT boxes; the reported RPs hold "
          f"{tot['instances']} instances: {tot['pass']} pass IOD > 0.5, {tot['on_object_fail']} "
          f"more have their centre on a GT object")
    share = np.concatenate(shares) if shares else np.zeros(0)
    share = share[np.isfinite(share)]
    print(f"  {len(share)} have their centre on a GT object; median area / the object's: "
          + (f"{np.median(share):.2f}" if len(share) else "-"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
