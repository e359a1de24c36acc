"""How far can the dense source's blobs go? Their coverage of the ground truth, a linear
probe on their features, and a self-supervised extension of the dense RPs over them.

The dense source (:mod:`rescu.extension.dense`) groups the image's strongest
centre-surround blobs (:func:`rescu.extension.dense.distinct_blobs`) into at most
``max_patterns`` RPs. ``feature_probe.py`` asks what stage II's *proposals* allow; this
study asks the same of the *blobs*, with the config's ``dense`` settings, on every image
of one dataset of a finished run:

1. **Coverage.** For every GT RP of ``--min-instances`` or more boxes, the share of its
   boxes that some blob covers (IOD > ``--iod``, the metric's test).
2. **Probe.** Its GT instances split in two halves at random (seeded). A balanced
   logistic regression on the blobs' unit mean features learns the blobs on the first
   half against half of the blobs on no box of that RP, then ranks the blobs on the
   second half against the other half of those. The figure is the share of the second
   half's GT boxes covered by a blob ranked above the point where blob precision falls
   below ``--precision`` (the cut is chosen with the ground truth: a bound). The probe is
   trained on half the GT (ideal labels), and on the blobs of the run's dense RP that the
   metric assigns to that GT RP (the labels the source has; GT RPs with none are left
   out of that row).
3. **Extension.** What the probe's idea gives without ground truth: each selected dense
   RP (recomputed here, equal to the run's) learns its own blobs against every other
   blob, cross-fitted (``--folds`` parts; a blob is scored by the model that did not see
   it as a negative), and takes in the blobs of probability >= each ``--threshold``
   (a blob claimed by two RPs goes to the more probable). Instance P / R of the RPs so
   extended, mean over images as the tables take it (an image without GT RP counts in
   precision only; :func:`rescu.evaluation.metrics.score_image`), beside the RPs as
   selected.

``--set KEY=VALUE`` changes a ``dense`` setting (e.g. ``objectness_crops=0``: the
ranking before objectness). Reads ``<results>/<dataset>/prepared`` and ``dense`` (a run
with ``dense.enabled``).
Asserts nothing. About a second per image.

Usage (after a run with the dense source, from the repository root)::

    python benchmarks/studies/blob_probe.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars --threshold 0.5 --threshold 0.7
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import numpy as np

# the checkout's rescu package, then benchmarks/ for the shared _cli.py and feature_probe
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1]),
                str(Path(__file__).resolve().parent)]


def blob_split(blobs: np.ndarray, gt: np.ndarray, train: np.ndarray | None,
               rng: np.random.Generator, h: float = 0.5
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The probe's train and test blobs for one GT RP.

    Parameters
    ----------
    blobs : (n, 4) float, ``[x, y, w, h]``
    gt : (G, 4) float, the GT RP's boxes (same pixels)
    train : (n,) bool or None
        The blobs to learn as positives (a dense RP's); None: those covering the first
        half of ``gt`` (ideal labels).
    rng : the split of ``gt`` and of the negatives
    h : IOD a blob needs on a GT box to lie on it

    Returns
    -------
    ``(positives, negatives, test, y, cover)`` as :func:`feature_probe.probe_split`: blob
    indices to train on, the test blobs, their (T,) 0 / 1 labels and (T, M) bool, which of
    the second half's M GT boxes each covers. The negatives (blobs on no box of ``gt``,
    not in ``train``) are split in two halves, one to train and one to test. None when
    no blob lies on the second half, or there is no positive or too few negatives.
    """
    from rescu.evaluation.metrics import iod_matrix

    on = iod_matrix(blobs, gt) > h
    perm = rng.permutation(len(gt))
    first, second = perm[: len(gt) // 2], perm[len(gt) // 2:]
    test_pos = on[:, second].any(1)
    ref = on[:, first].any(1) if train is None else np.asarray(train, bool)
    pos = np.flatnonzero(ref & ~test_pos)
    neg = np.flatnonzero(~on.any(1) & ~ref)
    if not test_pos.any() or not len(pos) or len(neg) < 2:
        return None
    neg = rng.permutation(neg)
    ntr, nte = np.sort(neg[: len(neg) // 2]), np.sort(neg[len(neg) // 2:])
    test = np.r_[np.flatnonzero(test_pos), nte]
    y = np.r_[np.ones(test_pos.sum(), int), np.zeros(len(nte), int)]
    return pos, ntr, test, y, on[test][:, second]


def crossfit_extend(emb: np.ndarray, groups: Sequence[np.ndarray], threshold: float,
                    folds: int = 5, seed: int = 0) -> list[np.ndarray]:
    """Each group of blobs extended by the blobs its own classifier accepts.

    Parameters
    ----------
    emb : (n, C) float, the blobs' features
    groups : index arrays into ``emb``, disjoint (the selected RPs' blobs)
    threshold : least cross-fitted probability a blob needs to join a group
    folds : the other blobs are scored in this many parts, each by a balanced logistic
        regression trained on the group against the other parts
    seed : the parts' random assignment (``seed + group index``)

    Returns
    -------
    one index array per group: its blobs, then the blobs it takes in (ascending); a blob
    of no group that two groups accept goes to the more probable (the first on a tie).

    >>> rng = np.random.default_rng(0)
    >>> emb = rng.normal(size=(60, 4))
    >>> emb[:12, 0] += 8.0                  # twelve blobs of one kind, four labelled
    >>> got = set(crossfit_extend(emb, [np.arange(4)], 0.5)[0].tolist())
    >>> got <= set(range(12)), len(got) >= 10     # unlabelled kin also act as negatives
    (True, True)
    """
    from sklearn.linear_model import LogisticRegression

    n = len(emb)
    taken = np.zeros(n, bool)
    for g in groups:
        taken[np.asarray(g, int)] = True
    best, owner = np.full(n, -np.inf), np.full(n, -1)
    for k, g in enumerate(groups):
        g = np.asarray(g, int)
        rest = np.flatnonzero(~np.isin(np.arange(n), g))
        if len(rest) < 2 or not len(g):
            continue
        part = np.random.default_rng(seed + k).permutation(len(rest)) % max(2, folds)
        prob = np.zeros(n)
        for q in np.unique(part):
            tr, te = rest[part != q], rest[part == q]
            clf = LogisticRegression(C=1.0, class_weight="balanced", max_iter=500)
            clf.fit(np.r_[emb[g], emb[tr]], np.r_[np.ones(len(g)), np.zeros(len(tr))])
            prob[te] = clf.predict_proba(emb[te])[:, 1]
        win = ~taken & (prob >= threshold) & (prob > best)
        best[win], owner[win] = prob[win], k
    return [np.r_[np.asarray(g, int), np.flatnonzero(owner == k)] for k, g in enumerate(groups)]


def main(argv: list[str] | None = None) -> int:
    import json

    import cv2

    from _cli import inputs_present, parse_sets, run_dataset, run_parser
    from feature_probe import probe

    from rescu import io
    from rescu.discovery.sources import DenseParams
    from rescu.evaluation.metrics import iod_matrix, iou_matrix, score_image
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.dense import dense_map, dense_patterns, distinct_blobs, objectness_for
    from rescu.io import load_coco_rps
    from rescu.params import deep_merge

    ap = run_parser(__doc__)
    ap.add_argument("--threshold", type=float, action="append", default=[],
                    help="extension probability (repeatable; default 0.5 0.7 0.9)")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--min-instances", type=int, default=4)
    ap.add_argument("--precision", type=float, default=0.7)
    ap.add_argument("--iod", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a dense setting other than the config's (repeatable)")
    a = ap.parse_args(argv)
    thresholds = a.threshold or [0.5, 0.7, 0.9]
    if a.min_instances < 2:
        ap.error(f"--min-instances must be >= 2 (two halves), got {a.min_instances}")
    if not 0 < a.precision <= 1 or not 0 <= a.iod < 1 or a.folds < 2:
        ap.error("--precision must be in (0, 1], --iod in [0, 1) and --folds >= 2")
    if not all(0 <= t <= 1 for t in thresholds):
        ap.error(f"--threshold must be in [0, 1], got {thresholds}")
    cfg, data = run_dataset(ap, a)
    try:
        params = DenseParams.from_dict(deep_merge(dict(cfg["dense"], enabled=True),
                                                  parse_sets(a.sets)))
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    run = a.results / a.dataset
    if not inputs_present((data / "annotations.json", "ground truth"),
                          (run / "prepared", "prepared images"),
                          (run / "dense", "dense RPs (a run with dense.enabled)")):
        return 2
    net = FrozenBackbone(params.backbone, feature_stride=16)
    cover: list[float] = []
    probes: dict[str, list[tuple[float, float, float]]] = {"half the GT": [], "dense RP": []}
    scores: dict[str, list[tuple[float, float]]] = {"as selected": []}
    scores.update({f"extended, p >= {t:g}": [] for t in thresholds})
    n = 0
    for i, (f, gts) in enumerate(load_coco_rps(data / "annotations.json").items()):
        stem = Path(f).stem
        png, dj = run / "prepared" / f"{stem}.png", run / "dense" / f"{stem}.json"
        if not png.is_file() or not dj.is_file():
            print(f"{f}: no prepared image or dense result, skipped", file=sys.stderr)
            continue
        meta = json.loads((run / "prepared" / f"{stem}.meta.json").read_text())
        rgb = np.ascontiguousarray(cv2.imread(str(png))[:, :, ::-1])
        fmap, s = dense_map(rgb, params, net)
        boxes, emb = distinct_blobs(fmap, 8.0, params)
        groups = [np.flatnonzero((iou_matrix(boxes, b) > 0.999).any(1)) if len(boxes) else
                  np.zeros(0, int) for _, b in dense_patterns(
                      fmap, 8.0, params, objectness_for(rgb, s, params, net))]
        boxes = boxes / (s * float(meta["scale_factor"]))      # original pixels
        gt_rps = [g.boxes for g in gts]
        dense = [[ins.bbox for ins in p.instances] for p in io.read_result(dj).patterns]
        assign = score_image(dense, gt_rps, a.iod).rp_assignment if dense and gt_rps else []
        for g, gb in enumerate(gt_rps):
            gt = np.asarray(gb, float).reshape(-1, 4)
            if len(gt) < a.min_instances or not len(boxes):
                continue
            cover.append(float((iod_matrix(boxes, gt) > a.iod).any(0).mean()))
            mine = [k for k, x in enumerate(assign) if x == g]
            labels = {"half the GT": None}
            if mine:
                d = np.asarray(dense[mine[0]], float).reshape(-1, 4)
                labels["dense RP"] = (iou_matrix(boxes, d) > 0.5).any(1)
            for name, train in labels.items():
                split = blob_split(boxes, gt, train, np.random.default_rng([a.seed, i, g]), a.iod)
                if split is not None:
                    probes[name].append(probe(emb, split, a.precision))
        for name, t in zip(scores, [None, *thresholds]):
            sel = groups if t is None else crossfit_extend(emb, groups, t, a.folds, a.seed)
            sc = score_image([boxes[k].tolist() for k in sel], gt_rps, a.iod)
            scores[name].append((sc.instance_precision, sc.instance_recall))
        n += 1
    print(f"## {a.dataset}: {n} images, {len(cover)} GT RPs of {a.min_instances}+ boxes\n")
    print(f"GT boxes some blob covers (IOD > {a.iod}): {np.mean(cover) if cover else np.nan:.3f}"
          "\n")
    print(f"| probe trained on | GT RPs | AP | GT boxes found at blob precision {a.precision} |")
    print("|---|---:|---:|---:|")
    for name, v in probes.items():
        r = np.asarray(v, float).reshape(-1, 3)
        ap_, _, found = r.mean(0) if len(r) else (np.nan,) * 3
        print(f"| {name} | {len(r)} | {ap_:.3f} | {found:.3f} |")
    print("\n| dense RPs | instance P | instance R |\n|---|---:|---:|")
    for name, v in scores.items():
        r = np.asarray(v, float).reshape(-1, 2)
        p_, r_ = np.nanmean(r, 0) if len(r) else (np.nan, np.nan)
        print(f"| {name} | {p_:.3f} | {r_:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
