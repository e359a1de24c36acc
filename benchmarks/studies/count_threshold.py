"""Which finds of "count these" to keep: threshold rules, fitted leave-one-set-out.

Reads the candidates saved by ``benchmarks/count_these.py --save FILE`` (every peak of
the final correlation with its score, the examples' reference score and the ground
truth) and scores threshold rules on them:

- ``abs t``: keep a find scoring at least ``t`` (cosine);
- ``rel r``: at least ``r`` x the examples' own score against the final template;
- ``norm r``: at least ``b + r (ref - b)``, ``b`` the photo's median score (the
  prompt section's ``relative_score``);
- ``otsu``: Otsu's split of the photo's candidate scores (plus the reference);
- ``gap``: the largest drop between consecutive sorted scores above the floor.

For each rule with a parameter, the parameter is chosen on all sets but one (most photos
counted within 10 %, ties: mean F1) and reported on the one left out, so every figure is
out of sample for its set; then the ceiling of any threshold rule (each photo's best
threshold, chosen with its ground truth). Prints per set and pooled coverage, precision, median count
error and the share within 10 % / 20 %; asserts nothing.

Usage (from the repository root)::

    python benchmarks/count_these.py --save /tmp/cands.json
    python benchmarks/studies/count_threshold.py /tmp/cands.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2])]


def keep(rule: str, par: float, scores: np.ndarray, ref: float, bg: float = 0.0
         ) -> np.ndarray:
    """Which of ``scores`` the rule keeps."""
    if rule == "abs":
        return scores >= par
    if rule == "rel":
        return scores >= par * ref
    if rule == "norm":
        return scores >= bg + par * (ref - bg)
    if rule == "otsu":
        from rescu.extension.prompted import otsu_split
        return scores >= otsu_split(np.r_[scores, ref])
    if rule == "gap":
        s = np.sort(scores)[::-1]
        if len(s) < 2:
            return scores >= 0
        d = s[:-1] - s[1:]
        return scores >= s[int(np.argmax(d))]
    raise ValueError(rule)


def image_row(d: dict, rule: str, par: float) -> tuple[int, int, int]:
    from rescu.evaluation.metrics import match_boxes

    gt = np.asarray(d["gt"]).reshape(-1, 4)
    ex = np.asarray(d["examples"]).reshape(-1, 4)
    c = np.asarray(d["candidates"]).reshape(-1, 4)
    s = np.asarray(d["scores"])
    k = keep(rule, par, s, d["reference"], d.get("background", 0.0)) if len(s) else np.zeros(0, bool)
    det = np.r_[ex, c[k]]
    return len(gt), len(det), len(match_boxes(det, gt, 0.5))


def figures(rows: list[tuple[int, int, int]]) -> dict:
    n_gt, n_det, n_m = (sum(r[i] for r in rows) for i in range(3))
    err = np.array([abs(d - g) / g for g, d, _ in rows])
    f1 = np.array([2 * m / (g + d) for g, d, m in rows])
    return {"coverage": n_m / n_gt, "precision": n_m / max(n_det, 1),
            "median_err": float(np.median(err)), "within10": float((err <= 0.1 + 1e-9).mean()),
            "within20": float((err <= 0.2 + 1e-9).mean()), "f1": float(f1.mean())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("candidates", type=Path)
    a = ap.parse_args(argv)
    data = json.loads(a.candidates.read_text())
    sets = sorted({k.split("/", 1)[0] for k in data})
    by_set = {s: [v for k, v in data.items() if k.split("/", 1)[0] == s] for s in sets}
    grids = {"abs": np.round(np.arange(0.30, 0.86, 0.025), 3),
             "rel": np.round(np.arange(0.40, 1.01, 0.025), 3),
             "norm": np.round(np.arange(0.20, 1.01, 0.025), 3),
             "otsu": [0.0], "gap": [0.0]}
    cache = {(r, p, s): [image_row(d, r, p) for d in by_set[s]]
             for r, g in grids.items() for p in g for s in sets}
    for rule, grid in grids.items():
        print(f"\n{rule}: parameter chosen leave-one-set-out")
        pooled = []
        for s in sets:
            others = [o for o in sets if o != s]

            def score(p):
                f = figures([r for o in others for r in cache[(rule, p, o)]])
                return f["within10"], f["f1"]
            best = max(grid, key=score)
            rows = cache[(rule, best, s)]
            pooled += rows
            f = figures(rows)
            print(f"  {s:12s} par {best:5.3f}  coverage {f['coverage']:.3f} precision "
                  f"{f['precision']:.3f} median err {f['median_err']:.3f} within 10% "
                  f"{f['within10']:.2f} 20% {f['within20']:.2f}")
        f = figures(pooled)
        print(f"  {'pooled':12s}            coverage {f['coverage']:.3f} precision "
              f"{f['precision']:.3f} median err {f['median_err']:.3f} within 10% "
              f"{f['within10']:.2f} 20% {f['within20']:.2f}")
    # the ceiling of every threshold rule: each photo's own best (F1) absolute threshold,
    # chosen with its ground truth; and what all candidates cover
    print("\noracle: each photo's best absolute threshold (ground truth used: an upper bound)")
    pooled, every = [], []
    for s in sets:
        rows = [max((cache[("abs", p, s)][i] for p in grids["abs"]),
                    key=lambda r: 2 * r[2] / (r[0] + r[1]))
                for i in range(len(by_set[s]))]
        allc = [image_row(d, "abs", -1.0) for d in by_set[s]]
        pooled += rows
        every += allc
        f, c = figures(rows), figures(allc)
        print(f"  {s:12s}            coverage {f['coverage']:.3f} precision "
              f"{f['precision']:.3f} median err {f['median_err']:.3f} within 10% "
              f"{f['within10']:.2f} 20% {f['within20']:.2f}  (every candidate: coverage "
              f"{c['coverage']:.3f})")
    f, c = figures(pooled), figures(every)
    print(f"  {'pooled':12s}            coverage {f['coverage']:.3f} precision "
          f"{f['precision']:.3f} median err {f['median_err']:.3f} within 10% "
          f"{f['within10']:.2f} 20% {f['within20']:.2f}  (every candidate: coverage "
          f"{c['coverage']:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
