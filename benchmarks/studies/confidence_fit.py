"""A confidence fitted on every set, checked leave-one-set-out (issue 85, item 1).

    python ../shared/tools/quick_eval.py run base --n 12 --sets cmp_facade,spb_facades,chess,\\
        aerial_cars,aquarium,blood_cells,nuclei,parking_lot          # once, on the code as it is
    python benchmarks/studies/confidence_fit.py results/quick/base [--json out.json]

Every RP a run generated for a photo, reported or set aside in ``candidate_patterns``,
is one sample. Its *label* says whether it is an RP of real objects: at least half of
its instances lie on ground-truth objects and at least two do. The objects are the
image's ``count_class`` boxes on the many-object sets (a box holds an object when the
object's centre lies inside it or near its centre: quick_eval's rule), and every GT RP
(boxes of one category, two or more; IOD > 0.5) on the RP sets; one to one. Its
*features* are what the run recorded without ground truth (:func:`features`).

A logistic regression on the features is fitted on seven sets and applied to the
eighth, for each set in turn; its output, the estimated probability that the RP is
one of real objects, is the *fitted confidence*. Printed per set:

* ROC AUC of the landed confidence and of the fitted one over the set's RPs (how well
  each ranks real RPs above the rest);
* the photos' dominant RP chosen again among all generated RPs by
  :func:`rescu.discovery.sources.split_by_confidence` with each confidence (and
  ``--threshold`` for the fitted one), then scored by quick_eval's own scoring:
  instance P / R of the reported RPs on the RP sets; cover, precision and median
  relative count error of the dominant RP on the many-object sets. ``--dominant
  count`` picks the most numerous reported RP of whole objects as dominant instead of
  the most confident (issue 85, item 2).

RPs set aside as ``tiling`` stay set aside (the board is not in the JSON). Needs
``../shared`` (quick_eval and the data); asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(Path(__file__).resolve().parent)]

from dominant_rules import _quick_eval  # noqa: E402

COUNT_SETS = ("aquarium", "blood_cells", "nuclei", "parking_lot")
RP_SETS = ("cmp_facade", "spb_facades", "chess", "aerial_cars")
NAMES = ("log_n", "gap", "log_contrast", "separation", "no_separation", "log_score",
         "dense", "log_resolution", "log_map_score", "log_area", "log_cover")
"""The features of :func:`features`, in order."""


def features(p: dict[str, Any], width: float, height: float) -> list[float]:
    """The features of one RP's JSON ``p`` in an image of ``width`` x ``height`` pixels:
    log instances (those it had when its confidence was scored: less the instances that
    completion and stage II added to a reported RP), the gap, log(1 + colour contrast),
    the separation (0 and a flag when not recorded), log of the dense ranking score
    (log 1e-4 when not recorded), whether it is a dense RP (whole objects), log of stage
    I's resolution and map score (0 when not recorded), log of the median box area over
    the image's and log of the share of the image the boxes cover."""
    b = np.array([i["bbox"] for i in p["instances"]], float).reshape(-1, 4)
    area = b[:, 2] * b[:, 3]
    sep = p.get("separation")
    added = sum(int(p.get(k) or 0) for k in ("completed", "stage2_added", "grid_completed"))
    return [math.log(max(len(b) - added, 1)), float(p.get("gap", 0.0)),
            math.log1p(max(float(p.get("contrast", 0.0)), 0.0)),
            0.0 if sep is None else float(sep), float(sep is None),
            math.log(max(float(p.get("score", 0.0) or 0.0), 1e-4)) if p.get("source") == "dense"
            else math.log(1e-4),
            float(p.get("source") == "dense"),
            math.log(max(float(p.get("resolution", 1.0)), 1e-3)),
            math.log(max(float(p.get("map_score", 1.0)), 1e-4)),
            math.log(max(float(np.median(area)) / (width * height), 1e-7)),
            math.log(max(min(float(area.sum()) / (width * height), 1.0), 1e-7))]


def gt_objects(root: Path, s: str) -> dict[str, tuple[np.ndarray, float]]:
    """GT objects of set ``s`` by photo stem: (m, 4) boxes and, on the many-object sets,
    quick_eval's centre radius (0 on the RP sets)."""
    coco = json.loads((root / s / "annotations.json").read_text())
    cat = {c["name"]: c["id"] for c in coco["categories"]}
    by: dict[int, dict[int, list]] = {}
    for an in coco["annotations"]:
        by.setdefault(an["image_id"], {}).setdefault(an["category_id"], []).append(an["bbox"])
    out = {}
    for im in coco["images"]:
        cats = by.get(im["id"], {})
        if s in COUNT_SETS:
            g = np.array(cats.get(cat.get(im.get("count_class")), []), float).reshape(-1, 4)
            if len(g) < 2:
                continue
            c = g[:, :2] + g[:, 2:] / 2
            d = np.hypot(*(c[:, None] - c[None]).transpose(2, 0, 1))
            np.fill_diagonal(d, np.inf)
            out[Path(im["file_name"]).stem] = (g, 0.5 * float(np.median(d.min(1))))
        else:
            g = [b for bs in cats.values() if len(bs) >= 2 for b in bs]
            if g:
                out[Path(im["file_name"]).stem] = (np.array(g, float).reshape(-1, 4), 0.0)
    return out


def matched(Q: Any, p: dict[str, Any], gt: tuple[np.ndarray, float]) -> int:
    """Instances of RP ``p`` on GT objects, one to one (quick_eval's rules)."""
    boxes = [i["bbox"] for i in p["instances"]]
    if not boxes:
        return 0
    g, rad = gt
    if rad > 0:
        return Q.centre_match(boxes, (g[:, :2] + g[:, 2:] / 2).tolist(), rad)
    return Q.matching(Q.iod(boxes, g) > 0.5)


def collect(Q: Any, run: Path, root: Path) -> list[dict[str, Any]]:
    """One row per photo of the run: its JSON, every generated RP's JSON, features and
    label."""
    rows = []
    for s in RP_SETS + COUNT_SETS:
        if not (run / s).is_dir():
            continue
        gts = gt_objects(root, s)
        for f in sorted((run / s).glob("*.json")):
            d = json.loads(f.read_text())
            if "patterns" not in d or f.stem not in gts:
                continue
            rps = [dict(p, dropped=None) for p in d["patterns"]] + list(
                d.get("candidate_patterns") or [])
            rps = [p for p in rps if p.get("instances")]
            x = [features(p, d["width"], d["height"]) for p in rps]
            m = [matched(Q, p, gts[f.stem]) for p in rps]
            y = [int(k >= 2 and k >= 0.5 * len(p["instances"])) for k, p in zip(m, rps)]
            rows.append({"set": s, "file": f.name, "json": d, "rps": rps, "x": x, "y": y})
    return rows


def fit_loso(rows: list[dict[str, Any]], C: float, balanced: bool = False) -> dict[str, Any]:
    """For each set, a logistic regression (standardised features, L2 with ``C``)
    fitted on the other sets' RPs; returns ``{set: model}`` and ``"all"``: one on every
    set (the one a default would use). Unweighted, its output is a calibrated
    probability; ``balanced`` weights the classes equally."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    sets = sorted({r["set"] for r in rows})
    models = {}
    for held in sets + ["all"]:
        X = [x for r in rows if r["set"] != held for x in r["x"]]
        y = [v for r in rows if r["set"] != held for v in r["y"]]
        lr = LogisticRegression(C=C, max_iter=2000,
                                class_weight="balanced" if balanced else None)
        models[held] = make_pipeline(StandardScaler(), lr).fit(np.array(X), np.array(y))
    return models


def auc(y: list[int], s: list[float]) -> float:
    """ROC AUC (ties half), nan without both labels."""
    y_, s_ = np.asarray(y), np.asarray(s, float)
    pos, neg = s_[y_ == 1], s_[y_ == 0]
    if not len(pos) or not len(neg):
        return float("nan")
    return float(((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum())
                 / (len(pos) * len(neg)))


def rescaled(p: dict[str, Any], scale: float, old: float) -> float:
    """The confidence RP ``p`` (JSON) would have had with the dense ranking-score term at
    ``scale`` instead of ``old`` (``dense.confidence_score_scale``; 0: not counted):
    the term is a factor of a dense RP's reported confidence
    (:func:`rescu.extension.objects.pattern_confidence`), stage I's RPs keep theirs."""
    from rescu.extension.objects import score_term

    c = float(p.get("confidence", 0.0))
    if p.get("source") != "dense":
        return c
    s = float(p.get("score") or 0.0)
    return c / max(score_term(s, old), 1e-12) * score_term(s, scale)


def reselect(row: dict[str, Any], conf: list[float], threshold: float, dominant: str,
             separation: bool) -> dict[str, Any]:
    """The photo's JSON with its RPs chosen again among every generated RP: each RP's
    confidence replaced by ``conf``, :func:`split_by_confidence` at ``threshold`` (the
    separation rule off unless ``separation``), the dominant RP by ``dominant``."""
    from rescu.discovery.sources import DenseParams, split_by_confidence
    from rescu.types import ImageResult

    d = row["json"]
    keep = [(p, c) for p, c in zip(row["rps"], conf) if p.get("dropped") != "tiling"]
    pats = [dict({k: v for k, v in p.items() if k != "dropped"}, confidence=float(c), id=k)
            for k, (p, c) in enumerate(keep)]
    res = ImageResult.from_json(dict(d, patterns=pats, candidate_patterns=[]))
    params = DenseParams.from_dict(None)
    if not separation:
        params = dataclasses.replace(params, min_object_separation=-2.0)
    split_by_confidence(res, threshold, params)
    out = dict(d, patterns=[p.to_json() for p in res.patterns])
    pick = None
    if res.patterns:
        pick = 0
        if dominant == "count":
            dense = [k for k, p in enumerate(res.patterns) if p.extra.get("source") == "dense"]
            if dense:
                pick = max(dense, key=lambda k: (res.patterns[k].count, -k))
    out["dominant_pattern"] = None if pick is None else int(res.patterns[pick].id)
    return out


def score(Q: Any, rows: list[dict[str, Any]], confs: list[list[float]], threshold: float,
          dominant: str, separation: bool, root: Path) -> dict[str, Any]:
    """quick_eval's table for the photos of ``rows`` chosen again (:func:`reselect`)."""
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        for r, c in zip(rows, confs):
            (base / r["set"]).mkdir(exist_ok=True)
            (base / r["set"] / r["file"]).write_text(json.dumps(
                reselect(r, c, threshold, dominant, separation)))
        return {s: (Q.score_rp if s in RP_SETS else Q.score_count)(root, s, base / s)
                for s in sorted({r["set"] for r in rows})}


NO_PATTERN = ("astronaut.png", "camera.png", "chelsea.png", "coffee.png", "moon.png",
              "motorcycle_left.png", "horse.png", "clock_motion.png", "retina.jpg",
              "grass.png", "gravel.png")
"""scikit-image's photos in which a person would name no recurring pattern of objects:
a portrait, a cat, a cup, a motorbike, a horse's silhouette, the moon, a retina, a
clock, and grass and gravel (textures, not objects)."""


def no_pattern_photos() -> list[Path]:
    """The paths of :data:`NO_PATTERN` in the installed scikit-image."""
    import skimage

    d = Path(skimage.__file__).parent / "data"
    return [d / n for n in NO_PATTERN]


def negatives(folder: Path) -> list[dict[str, Any]]:
    """Rows (as :func:`collect`'s, every RP labelled 0) of ``rescu discover`` results on
    :func:`no_pattern_photos` in ``folder``."""
    rows = []
    for f in sorted(folder.glob("*.json")):
        d = json.loads(f.read_text())
        if "patterns" not in d:
            continue
        rps = [p for p in [dict(p, dropped=None) for p in d["patterns"]]
               + list(d.get("candidate_patterns") or []) if p.get("instances")]
        rows.append({"set": "no pattern", "file": f.name, "json": d, "rps": rps,
                     "y": [0] * len(rps)})
    return rows


def components(rows: list[dict[str, Any]], root: Path) -> list[tuple[str, int, np.ndarray]]:
    """Per dense RP of ``rows`` (a run's and the negatives'): its set, label and
    ``[n, ranking score, box contrast, rarity against the photo's mean feature, rarity
    against the mean feature outside its boxes]``, on the photo's coarse map
    (:func:`rescu.extension.dense.dense_map`; the ranking score was taken on the map of
    the RP's level, so contrast x rarity here need not divide it)."""
    from rescu.config import load_config
    from rescu.core import prepare_file
    from rescu.discovery.sources import DenseParams
    from rescu.extension.boxmaps import box_contrast, box_features, integral_map, unit_mean
    from rescu.extension.dense import dense_map

    cfg = load_config(None)
    dp = DenseParams.from_dict(cfg["dense"])
    neg = {p.stem: p for p in no_pattern_photos()}
    out = []
    for r in rows:
        stem = Path(r["file"]).stem
        img = neg.get(stem) if r["set"] == "no pattern" else next(
            p for p in (root / r["set"] / "images").iterdir() if p.stem == stem)
        prep = prepare_file(img, max_side=cfg["image"]["max_side"],
                            min_side=cfg["image"]["min_side"])
        f, s = dense_map(prep.rgb, dp)
        k = float(prep.meta["scale_factor"]) * s
        ii, g = integral_map(f), unit_mean(f)
        for p, y in zip(r["rps"], r["y"]):
            if p.get("source") != "dense":
                continue
            b = np.array([i["bbox"] for i in p["instances"]], float) * k
            cen = box_features(f, 8.0, b, ii).mean(0)
            cen /= np.linalg.norm(cen) + 1e-12
            free = np.ones(f.shape[1:], bool)
            for x, yy, bw, bh in b / 8.0:
                free[max(0, int(yy)):int(np.ceil(yy + bh)),
                     max(0, int(x)):int(np.ceil(x + bw))] = False
            bg = f[:, free].mean(1) if free.any() else f.reshape(len(f), -1).mean(1)
            bg /= np.linalg.norm(bg) + 1e-12
            out.append((r["set"], y, np.array([len(b), float(p.get("score") or 0.0),
                                               float(box_contrast(f, b, 8.0, ii).mean()),
                                               1.0 - float(cen @ g), 1.0 - float(cen @ bg)])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, nargs="?",
                    help="a quick_eval run folder (results/quick/LABEL)")
    ap.add_argument("--threshold", type=float, default=0.5, help="fitted confidence to report")
    ap.add_argument("--C", type=float, default=0.3, help="inverse L2 strength")
    ap.add_argument("--score-scale", type=float, action="append", default=[],
                    help="also the landed confidence with the dense ranking-score term at "
                         "this scale (0: not counted; repeatable)")
    ap.add_argument("--balanced", action="store_true", help="weight the classes equally")
    ap.add_argument("--negatives", type=Path,
                    help="rescu discover results on the photos --list-negatives prints: "
                         "how many of them each variant would give an RP")
    ap.add_argument("--list-negatives", action="store_true",
                    help="print the paths of the photos without a pattern and stop")
    ap.add_argument("--components", action="store_true",
                    help="only the medians of the dense RPs' ranking-score components by "
                         "set and label (a backbone pass per photo)")
    ap.add_argument("--json", type=Path, help="write the tables here")
    a = ap.parse_args()
    if a.list_negatives:
        print(" ".join(map(str, no_pattern_photos())))
        return
    if a.run is None:
        ap.error("a run folder is needed")
    Q = _quick_eval()
    root = Q.shared_data()
    rows = collect(Q, a.run, root)
    neg = negatives(a.negatives) if a.negatives else []
    if a.components:
        got = components(rows + neg, root)
        print("set, label: dense RPs; medians of n, ranking score, box contrast, rarity "
              "(photo mean), rarity (outside the boxes)")
        for key in sorted({(s, y) for s, y, _ in got}):
            v = np.array([c for s, y, c in got if (s, y) == key])
            print(f"  {key[0]:12s} {key[1]}: {len(v):3d}  "
                  + "  ".join(f"{x:.3f}" for x in np.median(v, 0)))
        return
    models = fit_loso(rows, a.C, a.balanced)
    from rescu.discovery.sources import DenseParams
    dp = DenseParams.from_dict(None)
    t0, old = dp.min_confidence, dp.confidence_score_scale

    def fitted(rs: list[dict[str, Any]], held: str | None = None) -> list[list[float]]:
        return [list(models[held or r["set"]].predict_proba(np.array(
            [features(p, r["json"]["width"], r["json"]["height"]) for p in r["rps"]]))[:, 1])
                if r["rps"] else [] for r in rs]

    def landed(rs: list[dict[str, Any]], scale: float | None = None) -> list[list[float]]:
        return [[float(p.get("confidence", 0.0)) if scale is None else rescaled(p, scale, old)
                 for p in r["rps"]] for r in rs]

    report: dict[str, Any] = {"auc": {}, "tables": {}, "negatives": {}}
    fit = fitted(rows)
    for s in sorted({r["set"] for r in rows}):
        ys = [v for r in rows if r["set"] == s for v in r["y"]]
        report["auc"][s] = {"n_rps": len(ys), "real": int(sum(ys)),
                            "landed": auc(ys, [c for r, cs in zip(rows, landed(rows))
                                               if r["set"] == s for c in cs]),
                            "fitted": auc(ys, [c for r, cs in zip(rows, fit) if r["set"] == s
                                               for c in cs])}
    # name: (confidences of rows, of the negatives, threshold, dominant rule, separation rule)
    variants: dict[str, Any] = {
        "landed, as run": None,
        "landed, reselected": (landed(rows), landed(neg), t0, "first", True),
        "landed, no dense separation rule": (landed(rows), landed(neg), t0, "first", False)}
    for sc in a.score_scale:
        variants[f"landed, score term at {sc}"] = (landed(rows, sc), landed(neg, sc), t0,
                                                   "first", True)
        variants[f"landed, score term at {sc}, no dense separation rule"] = (
            landed(rows, sc), landed(neg, sc), t0, "first", False)
    variants.update({
        "fitted": (fit, fitted(neg, "all"), a.threshold, "first", True),
        "fitted, no dense separation rule": (fit, fitted(neg, "all"), a.threshold, "first",
                                             False),
        "fitted, dominant = most numerous whole objects": (fit, fitted(neg, "all"),
                                                           a.threshold, "count", False)})
    for name, v in variants.items():
        if v is None:
            report["tables"][name] = {s: (Q.score_rp if s in RP_SETS else Q.score_count)(
                root, s, a.run / s) for s in sorted({r["set"] for r in rows})}
            report["negatives"][name] = sorted(r["file"] for r in neg if r["json"]["patterns"])
            continue
        report["tables"][name] = score(Q, rows, v[0], v[2], v[3], v[4], root)
        report["negatives"][name] = sorted(
            r["file"] for r, c in zip(neg, v[1]) if reselect(r, c, v[2], v[3], v[4])["patterns"])
    print(f"{len(rows)} photos, {sum(len(r['y']) for r in rows)} RPs\n")
    print(f"{'set':12s} {'RPs':>5s} {'real':>5s}  AUC landed  fitted (left out)")
    for s, v in report["auc"].items():
        print(f"{s:12s} {v['n_rps']:5d} {v['real']:5d}  {v['landed']:.3f}       {v['fitted']:.3f}")
    for name, t in report["tables"].items():
        print(f"\n{name}")
        for s, row in t.items():
            print(f"  {s:12s} {Q.fmt(s, row)}")
        if neg:
            found = report["negatives"][name]
            print(f"  no pattern: {len(found)} of {len(neg)} photos with an RP "
                  f"{' '.join(Path(f).stem for f in found)}")
    m = models["all"]
    print("\nall-set model, standardised coefficients:",
          dict(zip(NAMES, m[-1].coef_[0].round(3).tolist())))
    if a.json:
        a.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
