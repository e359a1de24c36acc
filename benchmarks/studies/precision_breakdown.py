"""Where instance precision goes: every detected instance of a finished run, by what it lies on.

For each image of the dataset, each detected instance is credited by the paper's metric
(``assigned``), on an object of another GT RP (``other_rp``), a second detection on an
already matched GT box (``duplicate``) or on no GT box at all (``background``); and the
detected RPs whose every instance is background are counted
(:func:`_diagnostics.detection_breakdown`). Prints the totals over the
images and each share of the detected instances; with ``--images`` also one row per image,
and with ``--by-category`` one row per GT category: its GT boxes, the detections lying
on them (each on the smallest GT box it covers) and how many of those are duplicates
(:func:`_diagnostics.category_breakdown`). Asserts nothing.

Usage (after a run, from the repository root)::

    python benchmarks/studies/precision_breakdown.py results/realdev --config config/realdev.yaml \\
        --dataset spb_facades --method rescu-ii

``--method`` is the per-image JSON folder under ``<results>/<dataset>/`` (rescu-ii,
rescu-i, dense, final, ...). The dataset folder comes from the config, as in the run.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def main(argv: list[str] | None = None) -> int:
    from _cli import inputs_present, print_rows, run_dataset, run_parser

    from _diagnostics import (BREAKDOWN_COLUMNS, category_breakdown,
                                              precision_breakdown)

    ap = run_parser(__doc__)
    ap.add_argument("--method", default="rescu-ii", help="per-image JSON folder to break down")
    ap.add_argument("--images", action="store_true", help="also one row per image")
    ap.add_argument("--by-category", action="store_true",
                    help="also the detections and duplicates on each GT category")
    a = ap.parse_args(argv)
    _, data = run_dataset(ap, a)
    pred = a.results / a.dataset / a.method
    if not inputs_present((data / "annotations.json", "ground truth"), (pred, "predictions")):
        return 2
    df = precision_breakdown(data, pred)
    tot = df[list(BREAKDOWN_COLUMNS)].sum()
    n = max(int(tot["n_det"]), 1)
    print(f"{a.dataset} / {a.method}: {len(df)} images, {int(tot['n_det'])} detected "
          f"instances in {int(tot['n_rps'])} RPs")
    for k in ("assigned", "other_rp", "duplicate", "background"):
        print(f"  {k:<10} {int(tot[k]):>6}  {tot[k] / n:.3f}")
    print(f"  RPs with every instance on background: {int(tot['background_rps'])} of "
          f"{int(tot['n_rps'])}, holding {int(tot['background_rp_instances'])} instances "
          f"({tot['background_rp_instances'] / n:.3f})")
    if a.images:
        print_rows(df)
    if a.by_category:
        print()
        print_rows(category_breakdown(data, pred))
    return 0


if __name__ == "__main__":
    sys.exit(main())
