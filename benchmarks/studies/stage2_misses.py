"""Why stage II misses instances: every ground-truth instance RESCU-II does not find, by cause.

Reads a finished run: the ground truth, the RESCU-II JSONs and the stage-II artefacts
(``<results>/<dataset>/stage2/<image>.feats.h5`` and ``.head.h5``). A GT instance counts as
found when some RESCU-II instance (of any RP) covers it with IOD >= ``--iod`` (0.5, the
tables' h). Each GT instance not found gets one cause:

``rp not found``
    no instance of its GT RP is found at all: stage II only extends RPs stage I found.
``no lattice window``
    no lattice window (a window where an RP's instance lattice predicts an instance,
    ``stage2.proposals.lattice_windows``) covers it with IOD >= ``--iod``; with
    ``stage2.predict.lattice_only`` nothing else can add an instance.
``window p < 0.8`` / ``window p 0.8 - gate``
    the best such window's class probability (any RP's class, the per-image head) is
    under ``stage2.predict.lattice_score_threshold``.
``window p >= gate``
    a window scores above the gate and was dropped by another one (distance to the RP's
    centre, spacing to the other instances, size, non-maximum suppression).

Prints the counts per cause (and, on the synthetic benchmark, how many of the missed
instances are occluded) and, with ``--list``, one row per missed instance. Asserts
nothing; the causes use the run's own stage-II parameters from the config.

Usage (after ``snakemake --cores 2`` or ``make stress``, from the repository root)::

    python benchmarks/studies/stage2_misses.py results
    python benchmarks/studies/stage2_misses.py results/stress --list
    python benchmarks/studies/stage2_misses.py results --dataset cmp_facade
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

CAUSES = ("rp not found", "no lattice window", "window p < 0.8", "window p 0.8 - gate",
          "window p >= gate")


def _occluded(truth: dict[str, Any], box: Any) -> float | None:
    """Occluded fraction of the synthetic truth instance centred in ``box`` (None: no
    truth record there)."""
    from _diagnostics import truth_instance_at

    for p in truth.get("patterns") or []:
        t = truth_instance_at(p.get("instances") or [], box)
        if t is not None:
            return float(t.get("occluded_fraction") or 0.0)
    return None


def classify_misses(data: Path, results: Path, dataset: str, stage2: dict[str, Any],
                    iod: float = 0.5) -> Any:
    """One row per GT instance RESCU-II misses: ``image, gt_rp, x, y, w, h, cause,
    best_p, occluded_fraction`` (module docstring; ``attrs["gate"]``: the lattice gate
    used); an image without stage-II artefacts is skipped with a message on stderr."""
    import numpy as np
    import pandas as pd

    from rescu import io
    from rescu.extension.params import Stage2Params
    from rescu.extension.predict import score_proposals
    from rescu.extension.train import load_checkpoint
    from rescu.evaluation.core import load_predictions, load_truth
    from rescu.io import load_coco_rps
    from rescu.evaluation.metrics import iod_matrix

    params = Stage2Params.from_dict(stage2)
    gate = params.predict.lattice_score_threshold
    gt = load_coco_rps(data / "annotations.json")
    truth = load_truth(data)
    preds = load_predictions(results / dataset / "rescu-ii", gt.keys())
    rows: list[dict[str, Any]] = []
    for f, gts in gt.items():
        stem = Path(f).stem
        res = preds[f]
        h5 = results / dataset / "stage2" / f"{stem}.feats.h5"
        pt = results / dataset / "stage2" / f"{stem}.head.h5"
        if res is None or not h5.is_file() or not pt.is_file():
            print(f"{f}: no RESCU-II result or stage-II artefacts, skipped", file=sys.stderr)
            continue
        det = np.array([i.bbox for p in res.patterns for i in p.instances],
                       float).reshape(-1, 4)
        feats, _ = io.read_h5(h5)
        ckpt = load_checkpoint(pt)
        boxes = np.asarray(feats.get("proposals", np.zeros((0, 4))), float).reshape(-1, 4)
        lattice = np.asarray(feats.get("proposal_lattice", np.zeros(len(boxes)))
                             ).reshape(-1) > 0
        prob = (score_proposals(feats, ckpt["head"])
                if len(boxes) and "head" in ckpt else np.zeros((len(boxes), 1)))
        for g, rp in enumerate(gts):
            G = np.asarray(rp.boxes, float).reshape(-1, 4)
            found = ((iod_matrix(det, G) >= iod).any(0) if len(det)
                     else np.zeros(len(G), bool))
            for b in G[~found]:
                best = float("nan")
                if not found.any():
                    cause = "rp not found"
                else:
                    win = lattice & (iod_matrix(boxes, b[None])[:, 0] >= iod) if len(boxes) \
                        else np.zeros(0, bool)
                    if not win.any():
                        cause = "no lattice window"
                    else:
                        best = float(prob[win][:, 1:].max()) if prob.shape[1] > 1 else 0.0
                        cause = ("window p >= gate" if best >= gate else
                                 "window p 0.8 - gate" if best >= 0.8 else "window p < 0.8")
                rows.append({"image": f, "gt_rp": g, "x": b[0], "y": b[1], "w": b[2],
                             "h": b[3], "cause": cause, "best_p": best,
                             "occluded_fraction": _occluded(truth.get(f, {}), b)})
    cols = ["image", "gt_rp", "x", "y", "w", "h", "cause", "best_p", "occluded_fraction"]
    df = pd.DataFrame(rows, columns=cols)
    df.attrs["gate"] = gate
    return df


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from _cli import inputs_present, print_rows, run_dataset, run_parser

    ap = run_parser(__doc__)
    ap.add_argument("--iod", type=float, default=0.5, help="IOD for 'found' (default 0.5)")
    ap.add_argument("--list", action="store_true", help="one row per missed instance")
    a = ap.parse_args(argv)
    cfg, data = run_dataset(ap, a)
    if not inputs_present((data / "annotations.json", "ground truth"),
                          (a.results / a.dataset / "rescu-ii", "RESCU-II results")):
        return 2
    df = classify_misses(data, a.results, a.dataset, cfg["stage2"], a.iod)
    print(f"{a.dataset}: {len(df)} GT instances missed by RESCU-II (IOD {a.iod}; "
          f"lattice gate {df.attrs['gate']})")
    if df.empty:
        return 0
    occ = df["occluded_fraction"].fillna(0) > 0
    has_truth = df["occluded_fraction"].notna().any()
    out = pd.DataFrame({"missed": df["cause"].value_counts()}).reindex(CAUSES, fill_value=0)
    if has_truth:
        out["occluded"] = df[occ]["cause"].value_counts().reindex(CAUSES, fill_value=0)
    print(out.to_string())
    if a.list:
        print_rows(df)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
