"""Which RPs carry the precision: every RP of a finished run by source and confidence,
the RPs it set aside by reason, and its dominant RP against the largest GT RP.

For each image of a dataset with ground truth, each RP the run reports (and each one it
set aside in ``candidate_patterns``) has its instances matched one-to-one to every GT
box of the image (IOD > 0.5, :func:`rescu.evaluation.metrics.match_boxes`): the share
that lie on a GT object is the RP's precision against any GT RP. Prints, per dataset:

* the reported RPs by source (``stage1``: stage I's keypoint RPs; ``dense``: the dense
  source's whole objects) and confidence band: RPs, instances, share on GT objects;
* the RPs set aside, by the reason recorded (``low confidence``, ``one structure``,
  ``same objects``, ``overlap``): the same three figures;
* with ``--touching``: the reported RPs by source and by how many sides their
  instances abut another instance of the RP on average (:func:`rescu.boxes.touching_sides`
  at ``dense.touch_tolerance`` of the defaults, 0.35; the dense source drops its own RPs
  above ``dense.max_touching`` as tilings);
* the dominant RP (:func:`rescu.scene.counting.dominant_pattern`: the most confident,
  the one the caption counts) against the image's largest GT RP, over the images with a
  GT RP: the mean share of that GT RP it covers, its mean
  precision against it (images with an RP), the mean relative count error
  ``|count - GT count| / GT count`` (an image without an RP counts 0 instances) and the
  share of images where that error is at most 0.35. ``--dominant`` picks it by another
  rule among the image's reported RPs (:data:`DOMINANT`), to see what a rule would do
  without running the pipeline again; ``--dominant best`` picks, with the ground truth,
  the reported RP that covers the most of the largest GT RP (ties: the more precise):
  what no rule choosing among the reported RPs can beat.

Usage (after a run, from the repository root)::

    python benchmarks/studies/rp_sources.py results/realdev --config config/realdev.yaml \\
        --dataset chess --dataset aerial_cars --method rescu-ii [--touching]
    python benchmarks/studies/rp_sources.py results --dominant count-confidence

``--method`` is the per-image JSON folder under ``<results>/<dataset>/``. The dataset
folder comes from the config, as in the run. Asserts nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

BANDS = (0.0, 0.4, 0.6, 1.01)
"""Confidence bands of the reported RPs: [0, 0.4), [0.4, 0.6), [0.6, 1]."""

DOMINANT = {
    "code": None,
    "count": lambda n, c: (n, c),
    "count-confidence": lambda n, c: (n * c, n),
    "count-confidence3": lambda n, c: (n * c ** 3, n),
    "count-near-best": lambda n, c: (n, c),
    "objects": lambda n, c: (n, c),
}
"""Rules for the dominant RP: ``code`` is :func:`rescu.scene.counting.dominant_pattern`
(the most confident); the others rank an RP of ``n`` instances and confidence ``c`` by
the key they give (ties: the earlier RP), among the RPs whose confidence is at least
:data:`FLOOR` of the image's highest; ``objects`` only among the RPs of whole objects
(``extra["source"] == "dense"``), the most confident when there is none.
``--dominant`` also takes :data:`BEST`."""

BEST = "best"
"""The ``--dominant`` choice that looks at the ground truth (:func:`best_dominant`): an
upper bound on every rule, not a rule."""

TOUCH_BANDS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.01)
"""Bands of the mean number of abutting sides (of 4) of ``--touching``."""

FLOOR = {"count-near-best": 0.8}
"""Share of the image's highest confidence an RP needs to compete, by rule (0 when not
given): with ``count-near-best`` the count decides only between RPs the confidence
hardly tells apart."""


def pick_dominant(patterns: list[Any], rule: str = "code") -> int | None:
    """Index of the dominant RP of ``patterns`` by ``rule`` (:data:`DOMINANT`); None when
    no RP has an instance.

    >>> from rescu.types import Instance, Pattern
    >>> rp = lambda n, c: Pattern(id=0, score=1.0, extra={"confidence": c},
    ...                           instances=[Instance(bbox=(0, 0, 1, 1))] * n)
    >>> [pick_dominant([rp(3, 0.9), rp(20, 0.35)], r) for r in DOMINANT]
    [0, 1, 1, 0, 0, 0]
    >>> pick_dominant([rp(3, 0.9), rp(20, 0.75)], "count-near-best")
    1
    >>> dense = lambda n, c: Pattern(id=0, score=1.0, extra={"confidence": c, "source": "dense"},
    ...                              instances=[Instance(bbox=(0, 0, 1, 1))] * n)
    >>> pick_dominant([rp(30, 0.9), dense(4, 0.4), dense(9, 0.35)], "objects")
    2
    """
    from rescu.scene.counting import dominant_pattern

    key = DOMINANT[rule]
    if key is None:
        return dominant_pattern(patterns)
    if rule == "objects" and any(p.count and p.extra.get("source") == "dense"
                                 for p in patterns):
        return -max((p.count, float(p.extra.get("confidence", 0.0)), -k)
                    for k, p in enumerate(patterns)
                    if p.count and p.extra.get("source") == "dense")[2]
    if rule == "objects":
        return dominant_pattern(patterns)
    conf = [float(p.extra.get("confidence", 0.0)) for p in patterns]
    share = FLOOR.get(rule, 0.0)
    floor = share * max((c for c, p in zip(conf, patterns) if p.count), default=0.0)
    ranked = [(key(p.count, c), -k) for k, (p, c) in enumerate(zip(patterns, conf))
              if p.count and (share == 0.0 or c >= floor)]
    return -max(ranked)[1] if ranked else None


def best_dominant(patterns: list[Any], largest: Any) -> int | None:
    """Index of the RP of ``patterns`` whose instances cover the most of ``largest``
    ((m, 4) GT boxes; one-to-one, IOD > 0.5), ties: the higher share of its instances
    on them, then the earlier RP; None when none covers any.

    >>> from rescu.types import Instance, Pattern
    >>> rp = lambda boxes: Pattern(id=0, score=1.0, instances=[Instance(bbox=b) for b in boxes])
    >>> gt = [(0, 0, 10, 10), (20, 0, 10, 10)]
    >>> best_dominant([rp([(50, 50, 5, 5)] * 3), rp([(0, 0, 10, 10)]),
    ...                rp([(0, 0, 10, 10), (20, 0, 10, 10), (60, 60, 9, 9)])], gt)
    2
    >>> best_dominant([rp([(50, 50, 5, 5)])], gt) is None
    True
    """
    from rescu.evaluation.metrics import match_boxes

    gt = _boxes(list(largest))
    best: tuple[int, float, int] | None = None
    for k, p in enumerate(patterns):
        b = _boxes(p.instances)
        m = len(match_boxes(b, gt)) if len(b) and len(gt) else 0
        key = (m, m / max(len(b), 1), -k)
        if m and (best is None or key > best):
            best = key
    return None if best is None else -best[2]


def _boxes(items: list[Any]) -> Any:
    """(n, 4) float boxes of instances (objects or JSON dicts with ``bbox``) or boxes."""
    import numpy as np

    return np.array([i.bbox if hasattr(i, "bbox") else i["bbox"] if isinstance(i, dict)
                     else i for i in items], float).reshape(-1, 4)


def touching(boxes: Any, tolerance: float) -> float:
    """Mean :func:`rescu.boxes.touching_sides` of an RP's (n, 4) boxes at ``tolerance``
    (a fraction of the median box side): on how many of its 4 sides an instance abuts
    another."""
    from rescu.boxes import touching_sides

    return float(touching_sides(boxes, tolerance).mean())


def rp_rows(data: Path, pred: Path, rule: str = "code"
            ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``(rps, images)``: one row per RP of every image of ``data`` with a result in
    ``pred`` (``image, kind`` reported / set aside, ``source, confidence, reason, n,
    on_gt, touching``) and one per image (``gt_count`` of its largest GT RP, the dominant RP's
    ``count`` by ``rule`` (:func:`pick_dominant`), ``covered`` GT instances and
    ``on_largest`` of its own)."""
    from rescu.evaluation.metrics import match_boxes
    from rescu.io import load_coco_rps, read_result
    from rescu.params import config_defaults

    tol = config_defaults("dense")["touch_tolerance"]
    gt = load_coco_rps(data / "annotations.json")
    rps: list[dict[str, Any]] = []
    images: list[dict[str, Any]] = []
    for f, groups in gt.items():
        path = pred / (Path(f).stem + ".json")
        if not path.is_file():
            continue
        res = read_result(path)
        every = _boxes([b for g in groups for b in g.boxes])
        largest = max((g.boxes for g in groups), key=len, default=[])
        cands = res.extra.get("candidate_patterns") or []
        for kind, pats in (("reported", [(p.extra, p.instances) for p in res.patterns]),
                           ("set aside", [(c, c.get("instances", [])) for c in cands])):
            for extra, inst in pats:
                b = _boxes(inst)
                if not len(b):
                    continue
                rps.append({"image": f, "kind": kind, "touching": touching(b, tol),
                            "source": extra.get("source") or "stage1",
                            "confidence": extra.get("confidence"),
                            "reason": extra.get("dropped"), "n": len(b),
                            "on_gt": len(match_boxes(b, every)) if len(every) else 0})
        dom = (best_dominant(res.patterns, largest) if rule == BEST
               else pick_dominant(res.patterns, rule))
        row = {"image": f, "gt_count": len(largest), "count": 0, "covered": 0,
               "on_largest": 0}
        if dom is not None and len(largest):
            b = _boxes(res.patterns[dom].instances)
            m = len(match_boxes(b, _boxes(largest)))
            row.update(count=len(b), covered=m, on_largest=m)
        images.append(row)
    return rps, images


def dominant_summary(images: list[dict[str, Any]]) -> dict[str, float] | None:
    """Means over the images of :func:`rp_rows`' second list that have a GT RP: the share
    of the largest GT RP's objects the dominant RP covers (``covered``), its
    ``precision`` on them (over the images where it has instances; NaN where none has),
    the relative ``count_error`` and the share of images ``within_35`` (%) of the
    truth, and the number of ``images``; None when no image has a GT RP."""
    import numpy as np
    import pandas as pd

    im = pd.DataFrame(images, columns=["image", "gt_count", "count", "covered", "on_largest"])
    has = im[im.gt_count > 0]
    if not len(has):
        return None
    err = (has["count"] - has.gt_count).abs() / has.gt_count
    prec = np.where(has["count"] > 0, has.on_largest / has["count"].clip(lower=1), np.nan)
    return {"images": len(has), "covered": float((has.covered / has.gt_count).mean()),
            "precision": float(np.nanmean(prec)) if np.isfinite(prec).any() else float("nan"),
            "count_error": float(err.mean()), "within_35": float((err <= 0.35).mean())}


def _share(df: Any) -> str:
    n = int(df.n.sum())
    return f"{len(df):>5} RPs {n:>6} instances  on GT {df.on_gt.sum() / max(n, 1):.3f}"


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from _cli import set_predictions, sets_parser

    ap = sets_parser(__doc__)
    ap.add_argument("--dominant", choices=[*DOMINANT, BEST], default="code",
                    help="rule for the dominant RP (default: the code's, the most confident); "
                         "best: the one covering the most of the largest GT RP (uses the "
                         "ground truth: an upper bound on every rule)")
    ap.add_argument("--touching", action="store_true",
                    help="also the reported RPs by source and mean abutting sides")
    a = ap.parse_args(argv)
    sets = set_predictions(ap, a)
    if sets is None:
        return 2
    for ds, data, pred in sets:
        rows, imgs = rp_rows(data, pred, a.dominant)
        df = pd.DataFrame(rows, columns=["image", "kind", "source", "confidence", "reason",
                                         "n", "on_gt", "touching"])
        print(f"\n{ds} / {a.method}: {len(imgs)} images")
        rep = df[df.kind == "reported"]
        for src, g in rep.groupby("source"):
            print(f"  reported {src:<7} {_share(g)}")
            conf = pd.to_numeric(g.confidence, errors="coerce")
            for lo, hi in zip(BANDS[:-1], BANDS[1:]):
                band = g[(conf >= lo) & (conf < hi)]
                if len(band):
                    print(f"    confidence {lo:.1f}-{min(hi, 1.0):.1f} {_share(band)}")
        if a.touching:
            for src, g in rep.groupby("source"):
                for lo, hi in zip(TOUCH_BANDS[:-1], TOUCH_BANDS[1:]):
                    band = g[(g.touching >= lo) & (g.touching < hi)]
                    if len(band):
                        print(f"  reported {src:<7} abutting sides {lo:.2f}-{min(hi, 4.0):.2f} "
                              f"{_share(band)}")
        for why, g in df[df.kind == "set aside"].groupby("reason"):
            print(f"  set aside, {why:<15} {_share(g)}")
        d = dominant_summary(imgs)
        if d is not None:
            print(f"  dominant RP ({a.dominant}) vs the largest GT RP ({d['images']} images): "
                  f"covers {d['covered']:.3f}, precision {d['precision']:.3f}, "
                  f"relative count error {d['count_error']:.3f}, within 0.35 on "
                  f"{d['within_35']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
