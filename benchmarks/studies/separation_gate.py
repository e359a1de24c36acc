"""What a stricter separation gate would give: the any-RP instance figures of a finished
run after setting aside, as the gate would, the reported RPs whose recorded separation is
below each threshold.

For each dataset with ground truth and each threshold ``t``, every reported RP of the
run's per-image JSONs (``<results>/<dataset>/<method>/``) of the chosen ``--source``
(``dense``: the dense source's whole objects, the RPs ``dense.min_object_separation``
judges; ``stage1``: stage I's, ``dense.min_separation``; ``both``) whose
``separation`` (recorded by the pipeline; RPs without one, too few instances with a near
neighbour, are kept) is below ``t`` is dropped, and the rest are scored with
:func:`rescu.evaluation.core.evaluate_rp_dataset`. Prints, per threshold, each dataset's
mean any-RP instance precision / recall and the mean over datasets of their F1.

An approximation of rerunning with the gate at ``t``: in the pipeline an RP dropped by the
gate no longer takes objects from less confident RPs, which may then be reported, and
stage II learns from what RESCU-I reports. Use it to choose a threshold, then rerun
(``make realdev`` with the value) for the figures. Thresholds below the run's own gate
change nothing (those RPs were set aside already). Asserts nothing.

Usage (after ``make realdev``, from the repository root)::

    python benchmarks/studies/separation_gate.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars --dataset chess --dataset cmp_facade --dataset spb_facades \\
        --source dense --threshold 0.01 --threshold 0.05 --threshold 0.1
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def gated(result: dict[str, Any], threshold: float, source: str) -> dict[str, Any]:
    """``result`` (a per-image result's JSON) without its reported RPs of ``source``
    whose ``separation`` is below ``threshold``.

    >>> rp = lambda src, sep: {"source": src, "separation": sep, "instances": []}
    >>> r = {"patterns": [rp("dense", 0.05), rp("dense", None), rp(None, 0.0)]}
    >>> [(p["source"], p["separation"]) for p in gated(r, 0.1, "dense")["patterns"]]
    [('dense', None), (None, 0.0)]
    >>> len(gated(r, 0.1, "both")["patterns"])
    1
    """
    def keep(p: dict[str, Any]) -> bool:
        src = "dense" if p.get("source") == "dense" else "stage1"
        sep = p.get("separation")
        return sep is None or source not in (src, "both") or float(sep) >= threshold

    return {**result, "patterns": [p for p in result.get("patterns", []) if keep(p)]}


def gate_figures(data: Path, pred: Path, thresholds: list[float], source: str
                 ) -> list[tuple[float, float, float]]:
    """``(threshold, mean any-RP instance precision, mean recall)`` over the images of
    ``data`` for each threshold, the run's JSONs in ``pred`` gated by :func:`gated`."""
    from rescu.evaluation.core import evaluate_rp_dataset

    results = {f.name: json.loads(f.read_text()) for f in sorted(pred.glob("*.json"))}
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for t in thresholds:
            folder = Path(tmp) / f"t{len(out)}"
            folder.mkdir()
            for name, res in results.items():
                (folder / name).write_text(json.dumps(gated(res, t, source)))
            df = evaluate_rp_dataset(data, {"gated": folder})
            out.append((t, float(df.instance_precision_any.mean()),
                        float(df.instance_recall_any.mean())))
    return out


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    from _cli import f1, set_predictions, sets_parser

    ap = sets_parser(__doc__)
    ap.add_argument("--source", choices=["dense", "stage1", "both"], default="dense")
    ap.add_argument("--threshold", action="append", type=float, default=None,
                    help="separation threshold (repeat; default 0.01, 0.05, 0.1, 0.15)")
    a = ap.parse_args(argv)
    thresholds = a.threshold or [0.01, 0.05, 0.1, 0.15]
    rows: dict[str, list[tuple[float, float, float]]] = {}
    sets = set_predictions(ap, a)
    if sets is None:
        return 2
    for ds, data, pred in sets:
        rows[ds] = gate_figures(data, pred, thresholds, a.source)
    print(f"{a.method}, {a.source} RPs gated: any-RP instance P / R per dataset, mean F1")
    for k, t in enumerate(thresholds):
        cells = [f"{ds} {r[k][1]:.3f} / {r[k][2]:.3f}" for ds, r in rows.items()]
        mean_f1 = float(np.mean([f1(r[k][1], r[k][2]) for r in rows.values()]))
        print(f"  {t:+.3f}: " + "   ".join(cells) + f"   mean F1 {mean_f1:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
