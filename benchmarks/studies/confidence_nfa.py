"""An a-contrario confidence for RPs, measured on stored results (issue 85, item 1).

    python ../shared/tools/quick_eval.py run base --n 12 --sets ...   # once (see confidence_fit.py)
    python benchmarks/studies/confidence_nfa.py results/quick/base [--negatives DIR]

For every RP a run generated (reported or in ``candidate_patterns``) the photo is
prepared as the run did, its feature map made once (:func:`rescu.extension.dense.dense_map`),
and the RP's *number of false alarms* computed (:func:`nfa`): under the hypothesis that
the photo is made of windows drawn alike from its own background (the similarity map of
the RP's prototype away from its instances), how many windows as alike as the RP's
k-th most alike instance would one expect to find k of, minimised over k. The
instances' similarities are taken leave-one-out (each against the mean of the others),
so that an instance does not vouch for itself. The confidence is ``-log10 NFA``.

Printed: per set, ROC AUC of the landed confidence and of ``-log10 NFA`` over the
RPs (labels as :mod:`confidence_fit`), then quick_eval's table with the RPs chosen again
(:func:`confidence_fit.reselect`) at each ``--max-nfa``; with ``--negatives`` (folders
of ``rescu discover`` results on photos without an RP), the photos there that would
report an RP. Asserts nothing; needs ``../shared``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(Path(__file__).resolve().parent)]

import confidence_fit as cf  # noqa: E402


def log10_binom_tail(n: int, p: float, k: int) -> float:
    """log10 P[Bin(n, p) >= k] (0 for k <= 0).

    >>> round(log10_binom_tail(10, 0.5, 10), 3)
    -3.01
    """
    from scipy.stats import binom

    if k <= 0:
        return 0.0
    v = float(binom.logsf(k - 1, n, min(max(p, 1e-300), 1.0)))
    return v / math.log(10)


def nfa(f: np.ndarray, cell_px: float, boxes: np.ndarray, tests: float | None = None
        ) -> dict[str, float]:
    """The log10 number of false alarms of boxes ``(n, 4)`` (pixels of the map's input)
    recurring on the feature map ``f`` (C, h, w).

    Each instance's similarity is the cosine of its window's mean feature with the
    mean of the other instances' (leave one out); the background is the similarity map
    of the all-instance prototype at the median box size over the cells away from every
    box (:func:`rescu.extension.objects.distinctiveness`' free cells). With ``M`` =
    map area / box area disjoint windows, and ``p_k`` the share of background cells at
    least as similar as the k-th most similar instance, ``NFA = tests x min_k
    P[Bin(M, p_k) >= k]``, ``tests`` = ``M`` (the prototype could have been any window)
    unless given.
    """
    from rescu.extension.boxmaps import box_features, prototype_of
    from rescu.extension.objects import similarity_map

    b = np.asarray(boxes, float).reshape(-1, 4)
    n = len(b)
    if n < 2:
        return {"log_nfa": 0.0, "k": 0}
    emb = box_features(f, cell_px, b)
    proto, _, _, side = prototype_of(emb, b, cell_px)
    tot = emb.sum(0)
    loo = np.array([(emb[i] @ ((tot - emb[i]) / np.linalg.norm(tot - emb[i] + 1e-12)))
                    / (np.linalg.norm(emb[i]) + 1e-12) for i in range(n)])
    sim = similarity_map(f, proto, side)
    h, w = sim.shape
    free = np.ones(sim.shape, bool)
    for g in (0.5, 0.25, 0.0):
        free[:] = True
        for x, y, bw, bh in b:
            x0 = max(0, int(np.floor((x - g * bw) / cell_px)))
            y0 = max(0, int(np.floor((y - g * bh) / cell_px)))
            x1 = min(w, int(np.ceil((x + (1 + g) * bw) / cell_px)))
            y1 = min(h, int(np.ceil((y + (1 + g) * bh) / cell_px)))
            free[y0:y1, x0:x1] = False
        if free.mean() >= 0.05:
            break
    bg = np.sort(sim[free].ravel())
    if not len(bg):
        return {"log_nfa": 0.0, "k": 0}
    M = max(1, int(round(h * w / max(side[0] * side[1], 1))))
    s = np.sort(loo)[::-1]
    best, kbest = 0.0, 0
    for k in range(1, n + 1):
        above = len(bg) - np.searchsorted(bg, s[k - 1], side="left")
        p = (above + 1) / (len(bg) + 1)
        v = log10_binom_tail(M, p, k)
        if v < best:
            best, kbest = v, k
    t = M if tests is None else tests
    return {"log_nfa": best + math.log10(t), "k": kbest}


def photo_nfas(image: Path, rps: list[dict[str, Any]]) -> list[float]:
    """log10 NFA of every RP (JSON) of one photo's result."""
    from rescu.config import load_config
    from rescu.core import prepare_file
    from rescu.discovery.sources import DenseParams
    from rescu.extension.dense import dense_map

    cfg = load_config(None)
    prep = prepare_file(image, max_side=cfg["image"]["max_side"],
                        min_side=cfg["image"]["min_side"])
    dp = DenseParams.from_dict(cfg["dense"])
    f, s = dense_map(prep.rgb, dp)
    k = float(prep.meta["scale_factor"]) * s
    return [nfa(f, 8.0, np.array([i["bbox"] for i in p["instances"]], float) * k)["log_nfa"]
            for p in rps]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--negatives", type=Path,
                    help="rescu discover results on the photos of "
                         "confidence_fit.py --list-negatives")
    ap.add_argument("--max-nfa", type=float, action="append", default=[],
                    help="log10 NFA thresholds to report (repeatable; default 0 -2 -4)")
    ap.add_argument("--cache", type=Path,
                    default=Path("results/benchmarks/confidence_nfa/nfa.json"),
                    help="the NFAs computed, kept between runs")
    a = ap.parse_args()
    Q = cf._quick_eval()
    root = Q.shared_data()
    rows = cf.collect(Q, a.run, root)
    a.cache.parent.mkdir(parents=True, exist_ok=True)
    cache = json.loads(a.cache.read_text()) if a.cache.exists() else {}
    for r in rows:
        key = f"{r['set']}/{r['file']}"
        if key not in cache:
            img = root / r["set"] / "images"
            name = [p for p in img.iterdir() if p.stem == Path(r["file"]).stem][0]
            cache[key] = photo_nfas(name, r["rps"])
            a.cache.write_text(json.dumps(cache))
        r["nfa"] = cache[key]
    print(f"{'set':12s}  AUC landed  -log NFA")
    for s in sorted({r["set"] for r in rows}):
        ys = [v for r in rows if r["set"] == s for v in r["y"]]
        lc = [float(p.get("confidence", 0)) for r in rows if r["set"] == s for p in r["rps"]]
        nc = [-v for r in rows if r["set"] == s for v in r["nfa"]]
        print(f"{s:12s}  {cf.auc(ys, lc):.3f}       {cf.auc(ys, nc):.3f}")
    for t in a.max_nfa or [0.0, -2.0, -4.0]:
        confs = [[1.0 / (1.0 + math.exp(v - t)) for v in r["nfa"]] for r in rows]
        tab = cf.score(Q, rows, confs, 0.5, "first", True, root)
        print(f"\nlog10 NFA <= {t}")
        for s, row in tab.items():
            print(f"  {s:12s} {Q.fmt(s, row)}")
    photos = {p.stem: p for p in cf.no_pattern_photos()}
    for neg in [a.negatives] if a.negatives else []:
        for t in a.max_nfa or [0.0, -2.0, -4.0]:
            found = []
            for f in sorted(neg.glob("*.json")):
                d = json.loads(f.read_text())
                if "patterns" not in d:
                    continue
                rps = [p for p in d["patterns"] + (d.get("candidate_patterns") or [])
                       if p.get("instances")]
                key = f"neg/{f.stem}"
                if key not in cache:
                    cache[key] = photo_nfas(photos[f.stem], rps)
                    a.cache.write_text(json.dumps(cache))
                v = cache[key]
                if v and min(v) <= t:
                    n = len(rps[int(np.argmin(v))]["instances"])
                    found.append(f"{f.stem} ({min(v):.1f}, n={n})")
            print(f"{neg}: log10 NFA <= {t}: {len(found)} photos with an RP: {', '.join(found)}")


if __name__ == "__main__":
    main()
