"""What a separation gate would set aside: the separation of every reported RP of a
finished run, measured on the dense step's stored map, against its share on GT objects.

For each image of a dataset with ground truth, each RP that the run reports (in
``<results>/<dataset>/<method>/``) of the chosen source (``dense``: the dense source's
whole objects; ``stage1``: stage I's keypoint RPs) gets its separation
(:func:`rescu.extension.boxmaps.separation`, ``dense.separation_reach`` of the config)
with the given ``--probe``: 1 compares whole boxes, 1/3 their central thirds (what the
pipeline does for dense RPs, :data:`rescu.extension.boxmaps.OBJECT_PROBE`). It is measured
on the coarse map the dense step kept (``<dataset>/dense/<image>.map.h5``), whatever map
the RP was found on, so it can differ a little from the value the pipeline records. Its
instances are matched one-to-one to every GT box of the image (IOD > 0.5). Prints, per
dataset and threshold, the RPs below it, their instances and the share of those on GT
objects, beside the share of all the RPs' instances. Asserts nothing.

Usage (after ``make realdev``, from the repository root)::

    python benchmarks/studies/rp_separation.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars --dataset chess --method rescu-i --source dense \\
        --probe 0.3333 --threshold 0 --threshold 0.01
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def rp_separations(data: Path, run: Path, method: str, source: str, probe: float,
                   params: Any) -> list[dict[str, Any]]:
    """One row per reported RP of ``source`` of every image of ``data`` with a result in
    ``run/<method>`` and a stored map in ``run/dense``: ``image, n, on_gt, separation``
    (None when fewer than two instances have a near neighbour)."""
    import numpy as np

    from rescu.evaluation.metrics import match_boxes
    from rescu.extension.boxmaps import box_features, integral_map, separation
    from rescu.extension.dense import load_map
    from rescu.io import load_coco_rps, read_json, read_result

    rows: list[dict[str, Any]] = []
    for f, groups in load_coco_rps(data / "annotations.json").items():
        stem = Path(f).stem
        path, map_h5 = run / method / f"{stem}.json", run / "dense" / f"{stem}.map.h5"
        meta = run / "prepared" / f"{stem}.meta.json"
        if not (path.is_file() and map_h5.is_file() and meta.is_file()):
            continue
        stored = load_map(map_h5, params)
        if stored is None:
            continue
        fmap, s = stored
        ii = integral_map(fmap)
        scale = float(read_json(meta).get("scale_factor", 1.0))
        every = np.array([b.bbox if hasattr(b, "bbox") else b for g in groups for b in g.boxes],
                         float).reshape(-1, 4)
        for p in read_result(path).patterns:
            if (p.extra.get("source") or "stage1") != source:
                continue
            b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
            if len(b) < 2:
                continue
            m = b * scale * s                      # pixels of the map's input
            emb = box_features(fmap, 8.0, m, ii)
            proto = emb.mean(0)
            proto /= np.linalg.norm(proto) + 1e-9
            sep = separation(fmap, 8.0, m, proto, emb @ proto, params.separation_reach, ii,
                             probe=probe)
            rows.append({"image": f, "n": len(b), "separation": sep,
                         "on_gt": len(match_boxes(b, every)) if len(every) else 0})
    return rows


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from _cli import inputs_present, run_dataset, sets_parser
    from rescu.discovery.sources import DenseParams

    ap = sets_parser(__doc__, method="rescu-i")
    ap.add_argument("--source", choices=["dense", "stage1"], default="dense")
    ap.add_argument("--probe", type=float, default=1.0 / 3.0,
                    help="central part of each box compared, in (0, 1] (default 1/3)")
    ap.add_argument("--threshold", action="append", type=float, default=None,
                    help="separation threshold (repeat; default 0 and 0.01)")
    a = ap.parse_args(argv)
    if not 0 < a.probe <= 1:
        ap.error(f"--probe must be in (0, 1], got {a.probe}")
    for ds in a.datasets or ["synthetic"]:
        a.dataset = ds
        cfg, data = run_dataset(ap, a)
        run = a.results / ds
        if not inputs_present((data / "annotations.json", "ground truth"),
                              (run / a.method, "predictions"), (run / "dense", "dense step")):
            return 2
        df = pd.DataFrame(rp_separations(data, run, a.method, a.source, a.probe,
                                         DenseParams.from_dict(cfg["dense"])),
                          columns=["image", "n", "on_gt", "separation"])
        n = int(df.n.sum())
        print(f"\n{ds} / {a.method}, {a.source} RPs, probe {a.probe:.3f}: {len(df)} RPs, "
              f"{n} instances, on GT {df.on_gt.sum() / max(n, 1):.3f}")
        sep = pd.to_numeric(df.separation, errors="coerce")
        for t in a.threshold or [0.0, 0.01]:
            low = df[sep < t]
            k = int(low.n.sum())
            print(f"  below {t:+.3f}: {len(low):>4} RPs {k:>6} instances  on GT "
                  f"{low.on_gt.sum() / max(k, 1):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
