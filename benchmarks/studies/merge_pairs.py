"""Is RESCU-II's split-RP merge right? The merge evidence of every pair of stage-I RPs,
labelled by the ground truth.

For every image of a finished run with two or more stage-II RPs, computes
:func:`rescu.merge.pair_evidence` (the test ``rescu.stage2`` runs before merging, with
the config's ``stage2.predict.merge`` section) on the stored stage-I instance features
(``<results>/<dataset>/stage2/<image>.feats.h5``; those of the boxes before RESCU-I's
box refinement, as the merge) and boxes (``rescu-i/<image>.json``, the refinement undone),
and labels the pair *same* when both RPs are assigned to the same ground-truth RP,
*different* when to two, *unlabelled* when either is assigned to none
(:func:`rescu.evaluation.merge_pair_rows`: the RP-level matching of the tables). Prints the
pairs that pass the size, overlap-conflict and line gates (the appearance test decides
those), sorted by the appearance ratio ``S_AB / min(S_AA, S_BB)``, and a summary:
merges by label, same-RP pairs not merged, and the pairs that pass every test but
the line test (split grids, or rows of different RPs), those of two RPs of whole objects
(``max_object_line_residual``) apart. Asserts nothing.

The evidence is recomputed on the stage-I boxes; the pipeline's merge also sees the
stage-II instances' boxes in the conflict and line gates, so a pair can differ from the
``merged`` list of ``rescu-ii/<image>.json`` in those gates (never in the appearance).

Usage (after a run, from the repository root)::

    python benchmarks/studies/merge_pairs.py results                        # synthetic
    python benchmarks/studies/merge_pairs.py results/holdout-11
    python benchmarks/studies/merge_pairs.py results --dataset spb_facades
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from _cli import inputs_present, run_dataset, run_parser

    from _diagnostics import merge_pair_rows
    from rescu.io import load_coco_rps, read_h5, read_result
    from rescu.extension.merge import compared_features
    from rescu.extension.params import Stage2Params

    ap = run_parser(__doc__)
    ap.add_argument("--iod", type=float, default=0.5,
                    help="IOD threshold h of the RP-level matching")
    a = ap.parse_args(argv)
    cfg, data = run_dataset(ap, a)
    params = Stage2Params.from_dict(cfg["stage2"]).predict.merge.merge_params()
    ann = data / "annotations.json"
    s2 = a.results / a.dataset / "stage2"
    if not inputs_present((ann, "ground truth"), (s2, "stage-II features")):
        return 2
    truth = {Path(k).stem: v for k, v in load_coco_rps(ann).items()}
    rows = []
    for fh in sorted(s2.glob("*.feats.h5")):
        name = fh.name[:-len(".feats.h5")]
        arr, _ = read_h5(fh)
        rp_index = [int(v) for v in np.asarray(arr["rp_index"]).reshape(-1)]
        if len(rp_index) < 2:
            continue
        s1 = read_result(a.results / a.dataset / "rescu-i" / f"{name}.json")
        rows += [dict(image=name, **r) for r in merge_pair_rows(
            s1, rp_index, compared_features(arr), arr["instance_rp"], truth.get(name, []),
            params, a.iod)]
    df = pd.DataFrame(rows)
    if df.empty:
        print(f"{a.dataset}: no image with two or more stage-II RPs")
        return 0
    limit = np.where(df.objects, params.max_object_line_residual, params.max_line_residual)
    line_ok = pd.Series((limit <= 0) | (df.line_residual <= limit), index=df.index)
    gated = df[(df.size_ratio <= params.size_tolerance) & (df.conflicts == 0) & line_ok]
    pd.set_option("display.width", 250)
    pd.set_option("display.max_rows", None)
    print(f"{a.dataset}: {len(df)} RP pairs in {df.image.nunique()} images; {len(gated)} pass "
          f"the size / conflict / line gates (rho = {params.similarity_ratio}, "
          f"min S_AB = {params.min_similarity}):")
    if len(gated):
        print(gated.sort_values("ratio", ascending=False).round(3).to_string(index=False))
    m = df["merge"]
    known = (df.gt_a >= 0) & (df.gt_b >= 0)       # both RPs assigned to a GT RP
    diff = known & ~df.same

    def split(sel: pd.Series) -> str:
        return (f"same RP {int((sel & df.same).sum())}, different {int((sel & diff).sum())}, "
                f"unlabelled {int((sel & ~known).sum())}")

    looks = ((df.ratio >= params.similarity_ratio) & (df.s_ab >= params.min_similarity)
             & (df.size_ratio <= params.size_tolerance) & (df.conflicts == 0))
    for what, sel in (("rows", ~df.objects), ("whole objects", df.objects)):
        stopped = looks & ~line_ok & sel
        print(f"stopped by the line test alone, pairs of {what}: {int(stopped.sum())} "
              f"({split(stopped)})")
    print(f"merged: {int(m.sum())} ({split(m)}); same-RP pairs: {int(df.same.sum())}, not "
          f"merged {int((~m & df.same).sum())} "
          f"({int((~m & df.same & df.index.isin(gated.index)).sum())} of them stopped by the "
          f"appearance test)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
