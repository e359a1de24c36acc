"""Can stage II's frozen box features tell an RP's objects from the rest? A linear probe
with ground-truth labels.

Stage II's head learns each RP from the few instances stage I found
(``benchmarks/studies/stage2_gates.py`` shows it is where stage II loses most missed
instances). This study asks what the same features allow when the examples are perfect.
For every GT RP of ``--min-instances`` or more boxes in every image of one dataset of a
finished run, its GT instances are split in two halves at random (seeded). Then:

* a logistic regression (balanced classes) is trained on the box features of the
  proposals that fit the first half: for each GT instance, the proposal of highest IoU,
  and every proposal of IoU > 0.6. The negatives are up to 3000 proposals on no GT box
  of that RP (IOD <= ``--iod`` with every one);
* it is tested on the proposals of IoU > 0.5 with the second half (positives) against
  the other such negatives.

Each GT RP gives the average precision (AP) of that ranking, the recall at which the
ranking's precision is still at least ``--precision``, and the share of the second
half's GT boxes that some proposal ranked above that point covers (several proposals
may cover one box; this is the instance-level figure). The script prints their means
over GT RPs, and the same means for the probe *trained on stage I's RP* instead: the
proposals that fit the instances of the RESCU-I RP that the tables' RP-level matching
assigns to that GT RP (the first in RESCU-I's order when several are; GT RPs with none
are left out of that row). The first row
is a bound on the features with ideal labels. The second is the features with the
labels stage II has.

Features: ``stored`` is the run's own stage-II proposal features
(``stage2/<image>.feats.h5``). ``--variant`` adds features computed anew on the
prepared image at the run's backbone scale, from the EfficientNet-Lite0 maps:

* ``s16``: the stride-16 map, 2 x 2 RoI grid (what the default config stores);
* ``s32``: the stride-32 map (1280 channels), 1 x 1;
* ``hypercolumn``: the stride-8 and stride-16 maps, each 2 x 2 and L2-normalised,
  concatenated.

and two descriptors with no network, from the box's crop of the prepared image at full
resolution:

* ``hog``: the grey crop resized to 48 x 48 pixels, a histogram of oriented gradients
  (8-pixel cells, 16-pixel blocks, 9 bins; 900 values);
* ``pixels``: the crop resized to 12 x 12 pixels in CIE Lab, each channel centred
  (432 values).

Reads ``<results>/<dataset>/stage2``, ``rescu-i`` and (for a variant) ``prepared``.
Asserts nothing.

Usage (after a run, from the repository root)::

    python benchmarks/studies/feature_probe.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars --variant hypercolumn
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

VARIANTS = ("s16", "s32", "hypercolumn", "hog", "pixels")
MAX_NEGATIVES = 3000


def precise_prefix(y: np.ndarray, score: np.ndarray, precision: float) -> np.ndarray:
    """The items of the longest prefix of the ranking by ``score`` (descending) whose
    precision (share of ``y`` = 1) is at least ``precision``: (K,) indices, K = 0 when
    no prefix reaches it.

    >>> precise_prefix(np.array([1, 0, 1, 0]), np.array([4., 3., 2., 1.]), 0.6).tolist()
    [0, 1, 2]
    """
    order = np.argsort(-np.asarray(score, float), kind="stable")
    tp = np.cumsum(np.asarray(y, int)[order])
    ok = np.nonzero(tp / np.arange(1, len(order) + 1) >= precision)[0]
    return order[: ok[-1] + 1] if len(ok) else order[:0]


def recall_at_precision(y: np.ndarray, score: np.ndarray, precision: float) -> float:
    """The recall of :func:`precise_prefix`: the largest recall of the ranking at which
    precision is still at least ``precision``; 0 when no prefix reaches it.

    >>> recall_at_precision(np.array([1, 0, 1, 0]), np.array([4., 3., 2., 1.]), 0.6)
    1.0
    >>> recall_at_precision(np.array([0, 1]), np.array([2., 1.]), 0.7)
    0.0
    """
    y = np.asarray(y, int)
    if not y.sum():
        return 0.0
    return float(y[precise_prefix(y, score, precision)].sum() / y.sum())


def probe_split(proposals: np.ndarray, gt: np.ndarray, train_boxes: np.ndarray | None,
                rng: np.random.Generator, h: float = 0.5
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The probe's train and test proposals for one GT RP.

    Parameters
    ----------
    proposals : (P, 4) float, ``[x, y, w, h]``
    gt : (G, 4) float, the GT RP's boxes (same pixels)
    train_boxes : (N, 4) float or None
        Boxes whose fitting proposals are the positives (stage I's RP); None: the first
        half of ``gt`` (the oracle).
    rng : the split and the negative sample

    Returns
    -------
    ``(positives, negatives, test, y, cover)``: proposal indices to train on (positive
    and negative), the test proposals, their (T,) 0 / 1 labels and (T, M) bool: which of
    the second half's M GT boxes each covers (IoU > 0.5). None when the second half has
    no proposal of IoU > 0.5, or there are no positives or negatives.
    """
    from rescu.evaluation.metrics import iod_matrix, iou_matrix

    iou = iou_matrix(proposals, gt)
    neg = ~(iod_matrix(proposals, gt) > h).any(1)
    perm = rng.permutation(len(gt))
    first, second = perm[: len(gt) // 2], perm[len(gt) // 2:]
    test_pos = (iou[:, second] > 0.5).any(1)
    ref = iou[:, first] if train_boxes is None else iou_matrix(proposals, train_boxes)
    if not test_pos.any() or not ref.size or not neg.any():
        return None
    pos = np.unique(np.concatenate([ref.argmax(0), np.nonzero((ref > 0.6).any(1))[0]]))
    pos = pos[~test_pos[pos]]
    if not len(pos):
        return None
    ntr = np.nonzero(neg)[0]
    ntr = np.sort(rng.choice(ntr, min(len(ntr), MAX_NEGATIVES), replace=False))
    test = np.nonzero(test_pos | neg)[0]
    test = test[~np.isin(test, ntr)]
    return pos, ntr, test, test_pos[test].astype(int), iou[test][:, second] > 0.5


def probe(x: np.ndarray, split: tuple[np.ndarray, ...], precision: float
          ) -> tuple[float, float, float]:
    """A balanced logistic regression on features ``x`` (P, D) trained and tested on
    ``split`` (:func:`probe_split`): (AP over the test proposals, their recall at
    ``precision``, the share of the second half's GT boxes that some proposal of that
    precise prefix covers)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import average_precision_score

    pos, neg, test, y, cover = split
    clf = LogisticRegression(C=1.0, class_weight="balanced", max_iter=500)
    clf.fit(np.concatenate([x[pos], x[neg]]), np.r_[np.ones(len(pos)), np.zeros(len(neg))])
    s = clf.decision_function(x[test])
    found = cover[precise_prefix(y, s, precision)].any(0).mean() if cover.size else 0.0
    return (float(average_precision_score(y, s)), recall_at_precision(y, s, precision),
            float(found))


def fresh_features(variant: str, rgb: np.ndarray, boxes: np.ndarray, scale: float,
                   nets: dict[int, Any]) -> np.ndarray:
    """Box features of ``variant`` (:data:`VARIANTS`) for ``boxes`` (N, 4) in pixels of
    ``rgb`` (H, W, 3) uint8, the image resized by ``scale`` first; ``nets`` maps a stride
    (16, 32) to its :class:`rescu.extension.backbone.FrozenBackbone`. (N, D) float32,
    rows L2-normalised."""
    import cv2

    from rescu.extension.backbone import pool_boxes

    if variant in ("hog", "pixels"):
        return _crop_features(variant, rgb, boxes)
    h, w = rgb.shape[:2]
    nw, nh = max(16, round(w * scale)), max(16, round(h * scale))
    img = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA if scale < 1
                     else cv2.INTER_LINEAR)
    b = np.asarray(boxes, np.float32).reshape(-1, 4) * np.float32([nw / w, nh / h] * 2)
    if variant == "s16":
        parts = [pool_boxes(nets[16].feature_map(img), b, (nw, nh), 2)]
    elif variant == "s32":
        parts = [pool_boxes(nets[32].feature_map(img), b, (nw, nh), 1)]
    elif variant == "hypercolumn":
        f8, f16 = nets[16].multiscale_maps(img)
        parts = [pool_boxes(f8, b, (nw, nh), 2), pool_boxes(f16, b, (nw, nh), 2)]
    else:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    x = np.concatenate(parts, 1)
    return (x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-12)).astype(np.float32)


def _crop_features(variant: str, rgb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """``hog`` or ``pixels`` features (module docstring) of ``boxes`` (N, 4) ``[x, y, w,
    h]`` in pixels of ``rgb`` (H, W, 3) uint8: (N, D) float32, rows L2-normalised."""
    import cv2

    h, w = rgb.shape[:2]
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).astype(np.float32)
    hog = cv2.HOGDescriptor((48, 48), (16, 16), (8, 8), (8, 8), 9)
    rows = []
    for x, y, bw, bh in np.asarray(boxes, float).reshape(-1, 4):
        x0, y0 = int(np.clip(np.floor(x), 0, w - 1)), int(np.clip(np.floor(y), 0, h - 1))
        x1 = int(np.clip(np.ceil(x + bw), x0 + 1, w))
        y1 = int(np.clip(np.ceil(y + bh), y0 + 1, h))
        if variant == "hog":
            crop = cv2.resize(grey[y0:y1, x0:x1], (48, 48), interpolation=cv2.INTER_AREA)
            rows.append(hog.compute(crop).ravel())
        else:
            crop = cv2.resize(lab[y0:y1, x0:x1], (12, 12), interpolation=cv2.INTER_AREA)
            rows.append((crop - crop.reshape(-1, 3).mean(0)).ravel())
    x = np.asarray(rows, np.float32).reshape(len(rows), -1)
    return (x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-12)).astype(np.float32)


def image_probes(features: dict[str, np.ndarray], proposals: np.ndarray,
                 gt_rps: Sequence[Sequence[Sequence[float]]],
                 stage1_rps: Sequence[Sequence[Sequence[float]]], seed: Sequence[int],
                 min_instances: int = 4, precision: float = 0.7, h: float = 0.5
                 ) -> dict[str, list[tuple[float, float, float]]]:
    """``{"<features>": [(AP, recall, GT share), ...], "<features> stage I": [...]}``
    (:func:`probe`): one entry per
    GT RP of ``min_instances`` or more boxes of one image, for every feature set in
    ``features`` (name -> (P, D) array over ``proposals`` (P, 4))."""
    from rescu.evaluation.metrics import score_image

    out: dict[str, list[tuple[float, float, float]]] = {}
    for name in features:
        out[name], out[f"{name} stage I"] = [], []
    assign = score_image(stage1_rps, gt_rps, h).rp_assignment if stage1_rps else []
    for g, boxes in enumerate(gt_rps):
        gt = np.asarray(boxes, float).reshape(-1, 4)
        if len(gt) < min_instances:
            continue
        mine = [np.asarray(stage1_rps[i], float).reshape(-1, 4)
                for i, a in enumerate(assign) if a == g]
        for label, train in (("", None), (" stage I", mine[0] if mine else None)):
            if label and train is None:
                continue
            split = probe_split(proposals, gt, train,
                                np.random.default_rng(list(seed) + [g]), h)
            if split is None:
                continue
            for name, x in features.items():
                out[name + label].append(probe(x, split, precision))
    return out


def main(argv: list[str] | None = None) -> int:
    import json

    import cv2

    from _cli import inputs_present, run_dataset, run_parser

    from rescu import io
    from rescu.io import load_coco_rps

    ap = run_parser(__doc__)
    ap.add_argument("--variant", action="append", default=[], choices=VARIANTS,
                    help="features computed anew, besides the run's (repeatable)")
    ap.add_argument("--min-instances", type=int, default=4)
    ap.add_argument("--precision", type=float, default=0.7)
    ap.add_argument("--iod", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.min_instances < 2:
        ap.error(f"--min-instances must be >= 2 (two halves), got {a.min_instances}")
    if not 0 < a.precision <= 1:
        ap.error(f"--precision must be in (0, 1], got {a.precision}")
    if not 0 <= a.iod < 1:
        ap.error(f"--iod must be in [0, 1), got {a.iod}")
    _, data = run_dataset(ap, a)
    run = a.results / a.dataset
    if not inputs_present((data / "annotations.json", "ground truth"),
                          (run / "stage2", "stage-II features"),
                          (run / "rescu-i", "RESCU-I results")):
        return 2
    nets: dict[int, Any] = {}
    if set(a.variant) - {"hog", "pixels"}:
        from rescu.extension.backbone import FrozenBackbone

        nets = {16: FrozenBackbone(feature_stride=16), 32: FrozenBackbone(feature_stride=32)}
    totals: dict[str, list[tuple[float, float, float]]] = {}
    n = 0
    for i, (f, gts) in enumerate(load_coco_rps(data / "annotations.json").items()):
        stem = Path(f).stem
        fp, s1 = run / "stage2" / f"{stem}.feats.h5", run / "rescu-i" / f"{stem}.json"
        if not fp.is_file() or not s1.is_file():
            print(f"{f}: no stage-II features or RESCU-I result, skipped", file=sys.stderr)
            continue
        feats, _ = io.read_h5(fp)
        boxes = np.asarray(feats["proposals"], float).reshape(-1, 4)
        if not len(boxes):
            continue
        x = {"stored": np.asarray(feats["proposal_features"], np.float32)}
        if a.variant:
            meta = json.loads((run / "prepared" / f"{stem}.meta.json").read_text())
            bgr = cv2.imread(str(run / "prepared" / f"{stem}.png"))
            rgb = np.ascontiguousarray(bgr[:, :, ::-1])
            sf = float(meta["scale_factor"])       # proposals are in original pixels
            for v in a.variant:
                x[v] = fresh_features(v, rgb, boxes * sf, float(feats["backbone_scale"]), nets)
        det = [[ins.bbox for ins in p.instances] for p in io.read_result(s1).patterns]
        res = image_probes(x, boxes, [g.boxes for g in gts], det, (a.seed, i),
                           a.min_instances, a.precision, a.iod)
        for k, v in res.items():
            totals.setdefault(k, []).extend(v)
        n += 1
    print(f"## {a.dataset}: {n} images, GT RPs of {a.min_instances}+ boxes, linear probe\n")
    print(f"| features | trained on | GT RPs | AP | recall at precision {a.precision} "
          f"| GT boxes found at it |")
    print("|---|---|---:|---:|---:|---:|")
    for k, v in totals.items():
        name, on = (k[:-8], "stage I's RP") if k.endswith(" stage I") else (k, "half the GT")
        r = np.asarray(v, float).reshape(-1, 3)
        ap_, rec, found = (r.mean(0) if len(r) else (np.nan,) * 3)
        print(f"| {name} | {on} | {len(r)} | {ap_:.3f} | {rec:.3f} | {found:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
