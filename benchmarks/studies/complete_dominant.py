"""Completion by "count these": the dominant RP's instances as examples, on a quick_eval run.

    python ../shared/tools/quick_eval.py run base --n 12 --sets cmp_facade,spb_facades,\\
        chess,aerial_cars,aquarium,blood_cells,nuclei,parking_lot       # once
    python benchmarks/studies/complete_dominant.py results/quick/base [--seeds oracle] \\
        [--set relative_score=0.6 --set rounds=1]

The many-objects issue asks for a completion that finds every instance once a group is
accepted, and the "count these" issue for one implementation serving both. This study
measures what :func:`rescu.extension.prompted.find_like` (the prompted mode's search)
adds when its examples are an RP the run reported, without running the pipeline again:

* ``--seeds dominant`` (default): the examples are every instance of the photo's
  dominant RP (what the caption counts);
* ``--seeds oracle``: the reported RP with the most instances on ground-truth objects
  (quick_eval's matching: IOD > 0.5 on the RP sets, its centre rule on the many-object
  sets), and of it only those instances: completion seeded with right examples only,
  an upper bound on what a better choice of the dominant RP would get from it.

The finds that do not overlap an instance already there (cover at most 0.5 either way)
join the RP; the photo is prepared as ``rescu discover`` prepares it (longer side at
most ``image.max_side``), and the prompt section's settings, changed by ``--set
KEY=VALUE``, apply. The changed JSONs go to ``<run>/../complete-dominant/<name>/<set>/``
and are scored with quick_eval's own scoring next to the run's: instance precision and
recall over every reported RP on the RP sets; the dominant RP's cover, precision and
count errors on the many-object sets. Needs ``../shared`` (quick_eval and the data);
asserts nothing.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(Path(__file__).resolve().parent),
                str(Path(__file__).resolve().parents[1])]

import confidence_fit as cf  # noqa: E402
from _cli import parse_sets  # noqa: E402


def on_objects(Q: Any, boxes: np.ndarray, gt: tuple[np.ndarray, float]) -> np.ndarray:
    """Which of ``boxes`` (n, 4) lie on a ground-truth object of ``gt``
    (:func:`confidence_fit.gt_objects`): quick_eval's centre rule where ``gt`` has a radius
    (the many-object sets), IOD > 0.5 otherwise. Not one to one: a seed, not a score."""
    g, rad = gt
    b = np.asarray(boxes, float).reshape(-1, 4)
    if not len(b) or not len(g):
        return np.zeros(len(b), bool)
    if rad > 0:
        c = g[:, :2] + g[:, 2:] / 2
        inside = ((c[None, :, 0] >= b[:, None, 0]) & (c[None, :, 0] <= b[:, None, 0] + b[:, None, 2])
                  & (c[None, :, 1] >= b[:, None, 1]) & (c[None, :, 1] <= b[:, None, 1] + b[:, None, 3]))
        bc = b[:, :2] + b[:, 2:] / 2
        inside |= np.hypot(bc[:, None, 0] - c[None, :, 0], bc[:, None, 1] - c[None, :, 1]) <= rad
        return inside.any(1)
    return (np.asarray(Q.iod(b.tolist(), g.tolist())) > 0.5).any(1)


def seeds(Q: Any, d: dict[str, Any], how: str, gt: tuple[np.ndarray, float] | None
          ) -> tuple[int, list[dict[str, Any]]] | None:
    """The index in ``d["patterns"]`` of the RP to complete and its instances to use as
    examples (``how``: ``dominant`` or ``oracle``, see the module docstring); None when
    there is none (no dominant RP; for ``oracle``, no ground truth or fewer than two
    instances on objects)."""
    pats = d.get("patterns") or []
    if d.get("dominant_pattern") is None or not pats:
        return None
    if how == "dominant":
        k = next(i for i, p in enumerate(pats) if p["id"] == d["dominant_pattern"])
        return k, pats[k]["instances"]
    if gt is None:
        return None
    good = [on_objects(Q, np.array([i["bbox"] for i in p["instances"]], float), gt)
            for p in pats]
    k = max(range(len(pats)), key=lambda i: (int(good[i].sum()), -i))
    inst = [i for i, g in zip(pats[k]["instances"], good[k]) if g]
    return (k, inst) if len(inst) >= 2 else None


def complete(d: dict[str, Any], k: int, inst: list[dict[str, Any]], rgb: np.ndarray,
             scale: float, backbone: Any, params: Any) -> dict[str, Any]:
    """``d`` with RP ``k`` made of ``inst`` plus :func:`find_like`'s finds from them (the
    finds that overlap none of them by more than half either way) and made dominant;
    ``rgb`` the prepared photo, ``scale`` its pixels per original pixel."""
    from rescu.boxes import cover_matrix
    from rescu.extension.prompted import find_like

    h, w = rgb.shape[:2]
    ex = np.array([i["bbox"] for i in inst], float).reshape(-1, 4) * scale
    x0, y0 = np.clip(ex[:, 0], 0, w - 2), np.clip(ex[:, 1], 0, h - 2)
    ex = np.c_[x0, y0, np.minimum(ex[:, 2], w - x0), np.minimum(ex[:, 3], h - y0)]
    ok = (ex[:, 2] >= 2) & (ex[:, 3] >= 2)
    out = copy.deepcopy(d)
    p = out["patterns"][k]
    p["instances"] = [i for i, o in zip(copy.deepcopy(inst), ok) if o]
    ex = ex[ok]
    if len(ex) >= 1:
        found = find_like(rgb, ex, backbone, params)
        new, sc = found.boxes[~found.is_example], found.scores[~found.is_example]
        if len(new):
            apart = (cover_matrix(new, ex).max(1) <= 0.5) & (cover_matrix(ex, new).max(0) <= 0.5)
            new, sc = new[apart], sc[apart]
        p["instances"] += [{"bbox": [float(v) for v in b / scale], "score": float(c),
                            "source": "prompt"} for b, c in zip(new, sc)]
    p["count"] = len(p["instances"])
    out["dominant_pattern"] = p["id"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a quick_eval run folder (results/quick/LABEL)")
    ap.add_argument("--seeds", choices=("dominant", "oracle"), default="dominant")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a prompt setting changed (repeatable)")
    ap.add_argument("--name", default=None, help="output folder name (default from the options)")
    a = ap.parse_args()
    from rescu.config import load_config
    from rescu.core import prepare_file
    from rescu.extension.backbone import shared_backbone
    from rescu.extension.prompted import PromptParams

    Q = cf._quick_eval()
    root = Q.shared_data()
    cfg = load_config(None)
    params = PromptParams.from_dict({**cfg["prompt"], **parse_sets(a.set)})
    name = a.name or "-".join([a.seeds] + [s.replace("=", "") for s in a.set])
    out = a.run.parent / "complete-dominant" / name
    backbone = shared_backbone("efficientnet-lite0", feature_stride=16)
    sets = [s for s in cf.RP_SETS + cf.COUNT_SETS if (a.run / s).is_dir()]
    t0, done = time.perf_counter(), 0
    for s in sets:
        (out / s).mkdir(parents=True, exist_ok=True)
        gts = cf.gt_objects(root, s)
        photos = {p.stem: p for p in (root / s / "images").iterdir()}
        for f in sorted((a.run / s).glob("*.json")):
            d = json.loads(f.read_text())
            pick = seeds(Q, d, a.seeds, gts.get(f.stem)) if "patterns" in d else None
            if pick is not None:
                prep = prepare_file(photos[f.stem], max_side=cfg["image"]["max_side"],
                                    min_side=cfg["image"]["min_side"])
                d = complete(d, pick[0], pick[1], prep.rgb, float(prep.meta["scale_factor"]),
                             backbone, params)
                done += 1
            (out / s / f.name).write_text(json.dumps(d))
    print(f"{done} RPs completed in {time.perf_counter() - t0:.0f} s; results in {out}")
    print(f"{'set':12s} completed | the run")
    for s in sets:
        score = Q.score_rp if s in cf.RP_SETS else Q.score_count
        print(f"  {s:12s} {Q.fmt(s, score(root, s, out / s))} | {Q.fmt(s, score(root, s, a.run / s))}")


if __name__ == "__main__":
    main()
