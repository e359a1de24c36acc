"""Whether the ImageNet classifier's objectness tells stage I's RPs on objects from
stage I's RPs on stuff: every reported RP of a finished run scored, and the any-RP figures
with the stage-I RPs below a threshold left out.

The dense source ranks its groups by objectness (:func:`rescu.extension.dense.objectness`:
the frozen classifier's mean top-class probability on crops around an RP's first
instances); stage I's RPs have no such term. Here every RP each image reports (in
``<results>/<dataset>/<method>/``) gets it, on the run's prepared image, over its first
``--crops`` instances. Per dataset and source, it prints the RPs, the share of their
instances on a GT object (IOD > 0.5, one to one) and their median objectness. Then,
over stage I's RPs of all the datasets, the ROC AUC of objectness for two questions:
RPs with at least half their instances on GT objects against the others, and RPs on
the facade sets against RPs on chess. Last, for each ``--threshold``, the any-RP
instance precision / recall per dataset (:func:`rescu.evaluation.metrics.score_image`,
mean over the images, undefined values left out as in the RP table). These are
computed with the reported stage-I RPs whose objectness is below the threshold left
out. This is a simulation: a pipeline that dropped them could report other RPs in their
place. Asserts nothing.

Usage (after ``make realdev``, from the repository root)::

    python benchmarks/studies/rp_objectness.py results/realdev --config config/realdev.yaml \\
        --dataset chess --dataset cmp_facade --dataset spb_facades --dataset aerial_cars
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

FACADES = ("cmp_facade", "spb_facades")
"""The sets whose stage-I RPs are windows (against chess's, on the board)."""


def load_images(data: Path, pred: Path) -> list[tuple[str, list[Any], Any]]:
    """``(file name, GT RPs, result)`` of every image of ``data`` (its
    ``annotations.json``) with a result in ``pred``, read once for every figure."""
    from rescu.io import load_coco_rps, read_result

    out = []
    for f, groups in load_coco_rps(data / "annotations.json").items():
        path = pred / f"{Path(f).stem}.json"
        if path.is_file():
            out.append((f, groups, read_result(path)))
    return out


def rp_objectness(prepared: Path, ds: str, images: list[tuple[str, list[Any], Any]],
                  backbone: Any, params: Any) -> list[dict[str, Any]]:
    """One row per reported RP of ``images`` (:func:`load_images`): ``set`` (``ds``),
    ``image, k`` (its index), ``source``, ``n``, ``on_gt`` (instances on a GT object of a
    GT RP), ``objectness`` (on ``<prepared>/<image stem>.png``)."""
    import cv2
    import numpy as np

    from rescu.evaluation.metrics import match_boxes
    from rescu.extension.dense import objectness
    from rescu.io import read_json

    rows = []
    for f, groups, res in images:
        stem = Path(f).stem
        s = float(read_json(prepared / f"{stem}.meta.json")["scale_factor"])
        bgr = cv2.imread(str(prepared / f"{stem}.png"))
        if bgr is None:
            raise SystemExit(f"{prepared / (stem + '.png')}: missing or unreadable")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        every = np.array([b for g in groups for b in g.boxes], float).reshape(-1, 4)
        for k, p in enumerate(res.patterns):
            b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
            if not len(b):
                continue
            rows.append({"set": ds, "image": f, "k": k,
                         "source": p.extra.get("source") or "stage1", "n": len(b),
                         "on_gt": len(match_boxes(b, every)) if len(every) else 0,
                         "objectness": objectness(backbone, rgb, b * s, params)})
    return rows


def without_below(ds: str, images: list[tuple[str, list[Any], Any]],
                  drop: set[tuple[str, str, int]]) -> tuple[float, float]:
    """Mean any-RP instance precision and recall over ``images`` (:func:`load_images`
    of ``ds``), each image's RPs ``(ds, image, k)`` in ``drop`` left out."""
    import numpy as np

    from rescu.evaluation.metrics import score_image

    P, R = [], []
    for f, groups, res in images:
        det = [[i.bbox for i in p.instances] for k, p in enumerate(res.patterns)
               if (ds, f, k) not in drop]
        sc = score_image(det, [g.boxes for g in groups])
        P.append(sc.instance_precision_any)
        R.append(sc.instance_recall_any)
    with np.errstate(all="ignore"):
        return (float(np.nanmean(P)) if np.isfinite(P).any() else float("nan"),
                float(np.nanmean(R)) if np.isfinite(R).any() else float("nan"))


def auc(positive: Any, score: Any) -> float:
    """ROC AUC of ``score`` for the boolean ``positive``; NaN with one class only."""
    import numpy as np
    from sklearn.metrics import roc_auc_score

    y = np.asarray(positive, bool)
    return float(roc_auc_score(y, score)) if 0 < y.sum() < len(y) else float("nan")


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from _cli import set_predictions, sets_parser
    from rescu.discovery.sources import DenseParams
    from rescu.extension.backbone import FrozenBackbone
    from rescu.params import config_defaults

    ap = sets_parser(__doc__)
    ap.add_argument("--crops", type=int, default=8,
                    help="instances classified per RP (default 8)")
    ap.add_argument("--threshold", type=float, action="append", default=None,
                    help="objectness below which stage I's RPs are left out (repeatable; "
                         "default 0 0.2 0.3 0.4)")
    a = ap.parse_args(argv)
    if a.crops < 1:
        ap.error(f"--crops must be >= 1, got {a.crops}")
    sets = set_predictions(ap, a)
    if sets is None:
        return 2
    params = DenseParams.from_dict({**config_defaults("dense"), "objectness_crops": a.crops})
    backbone = FrozenBackbone(params.backbone, feature_stride=16)
    images = {ds: load_images(data, pred) for ds, data, pred in sets}
    rows = [r for ds, ims in images.items()
            for r in rp_objectness(a.results / ds / "prepared", ds, ims, backbone, params)]
    df = pd.DataFrame(rows, columns=["set", "image", "k", "source", "n", "on_gt",
                                     "objectness"])
    for (ds, src), g in df.groupby(["set", "source"]):
        print(f"{ds:<14} {src:<7} {len(g):>5} RPs, on GT {g.on_gt.sum() / g.n.sum():.3f}, "
              f"median objectness {g.objectness.median():.3f}")
    s1 = df[df.source == "stage1"]
    board = s1[s1.set.isin([*FACADES, "chess"])]
    print(f"stage-I RPs: AUC of objectness, half or more on GT against the others "
          f"{auc(s1.on_gt >= 0.5 * s1.n, s1.objectness):.3f}; facades against chess "
          f"{auc(board.set.isin(FACADES), board.objectness):.3f}")
    for t in a.threshold or [0.0, 0.2, 0.3, 0.4]:
        drop = set(map(tuple, s1[s1.objectness < t][["set", "image", "k"]].values.tolist()))
        figs = "  ".join(f"{ds} {p:.3f} / {r:.3f}" for ds, ims in images.items()
                         for p, r in [without_below(ds, ims, drop)])
        print(f"stage-I RPs below {t:.2f} left out ({len(drop)}): any-RP P / R {figs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
