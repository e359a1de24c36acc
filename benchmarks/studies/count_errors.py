"""Why counts are wrong: the instances behind every count error of a finished run.

For each ground-truth RP whose count is wrong (the counting table's exact-count rate
counts it as a miss), lists the GT instances the counting RP missed and the detected
instances that match none (with their source: stage1 / stage2 / completion), with the
synthetic benchmark's truth (row, column, occluded fraction, blur, equal spacing) where
the dataset has it (:func:`_diagnostics.count_errors`). Prints; asserts nothing.

Usage (after ``snakemake --cores 2``, from the repository root)::

    python benchmarks/studies/count_errors.py results                      # synthetic, final
    python benchmarks/studies/count_errors.py results/holdout --method rescu-ii
    python benchmarks/studies/count_errors.py results --dataset cmp_facade --all

``--method`` is the per-image JSON folder under ``<results>/<dataset>/`` (final,
rescu-ii, rescu-i, grasp, scene). The dataset folder comes from the
configuration (the defaults, or ``--config`` merged over them), as in the run.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def main(argv: list[str] | None = None) -> int:
    from _cli import inputs_present, print_rows, run_dataset, run_parser

    from _diagnostics import count_errors
    from rescu.evaluation.count_table import counting_table

    ap = run_parser(__doc__)
    ap.add_argument("--method", default="final", help="per-image JSON folder to evaluate")
    ap.add_argument("--all", action="store_true", help="also list the matched instances")
    a = ap.parse_args(argv)
    _, data = run_dataset(ap, a)
    pred = a.results / a.dataset / a.method
    if not inputs_present((data / "annotations.json", "ground truth"), (pred, "predictions")):
        return 2
    t = counting_table(data, {a.method: pred}).iloc[0]
    print(f"{a.dataset} / {a.method}: {int(t['n_matched'])} matched GT RPs, exact-count "
          f"rate {t['exact_rate']:.3f}, count MAE {t['count_mae']:.3f}")
    df = count_errors(data, pred)
    if df.empty:
        print("every count is exact")
        return 0
    if not a.all:
        df = df[df["kind"] != "matched"]
    df = df.dropna(axis=1, how="all")
    print_rows(df)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
