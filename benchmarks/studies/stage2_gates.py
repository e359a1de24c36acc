"""Where stage II loses the instances of RPs that stage I found well: its gates, in order.

For every image of one dataset of a finished run, takes each RESCU-I RP that the tables'
RP-level matching accepts for a GT RP (instance precision >= 0.5 against it, two or more
matches: :func:`rescu.evaluation.metrics.score_image`) and the instances of that GT RP
the RP does not cover (no instance of it with IOD > ``--iod``). Those are the instances
stage II is there to add. For each one, stage II's prediction gates
(:func:`rescu.extension.predict.predict_stage2`, with the run's ``stage2`` config) are
applied cumulatively to the proposals covering it (IOD > ``--iod``), and the count that
still has such a proposal after each gate is printed:

``missing``
    GT instances of accepted RPs' GT RPs, not covered by the RP (one row per RP and GT
    instance; ``not extended`` of them belong to RPs stage II does not extend).
``covered``
    some proposal (lattice window or instance-scale window) covers it.
``allowed``
    ... one that ``stage2.predict.lattice_only`` allows (a lattice window when true).
``argmax``
    ... whose head probability is highest for this RP.
``score``
    ... at least the gate (``lattice_score_threshold`` for lattice windows,
    ``score_threshold`` for the others).
``distance``
    ... within the feature-distance gate (``lattice_distance_ratio`` /
    ``max_distance_ratio`` x the RP's radius from one of its DBSCAN centres).
``size``
    ... whose size passes ``examples.size_tolerance`` against the RP's instances.
``added``
    an instance stage II added covers it: what passed suppression, spacing and
    ``max_new_fraction`` too. It may be another RP's new instance (or an RP's the
    merge joined), so this count can exceed the last gate's.

The column *any proposal* repeats the funnel with every proposal allowed (as if
``lattice_only`` were false). Reads ``<results>/<dataset>/rescu-i``, ``rescu-ii`` and
``stage2/<image>.feats.h5`` / ``.head.h5``; an image without them is skipped with a
message. Asserts nothing.

Usage (after a run, from the repository root)::

    python benchmarks/studies/stage2_gates.py results/realdev --config config/realdev.yaml \\
        --dataset aerial_cars
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

# the checkout's rescu package, then benchmarks/ for the shared _cli.py
sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]

STAGES = ("missing", "covered", "allowed", "argmax", "score", "distance", "size")
COUNTS = STAGES + ("not extended", "added")   # what image_funnels and the totals count


def gate_funnel(missing: np.ndarray, k: int, own: np.ndarray, boxes: np.ndarray,
                lattice: np.ndarray, prob: np.ndarray, distance: np.ndarray, radius: float,
                params: Any, lattice_only: bool, h: float = 0.5,
                whole_objects: bool = False) -> dict[str, int]:
    """How many of one RP's missing GT instances keep a covering proposal after each gate.

    Parameters
    ----------
    missing : (M, 4) float, ``[x, y, w, h]`` GT boxes the RP does not cover
    k : the RP's position in the stage-II features' ``rp_index`` (its class is k + 1)
    own : (N, 4) float, the RP's stage-I boxes (the size gate's reference)
    boxes : (P, 4) float, the proposals (same pixels as the boxes above)
    lattice : (P,) bool, lattice windows
    prob : (P, R + 1) float, head probabilities (column 0 background)
    distance : (P,) float, feature distance to the RP's nearest DBSCAN centre
    radius : float, the RP's radius in that space
    params : Stage2Params (``predict`` gates, ``examples.size_tolerance``)
    lattice_only : only lattice windows may add an instance (the ``allowed`` gate)
    h : IOD above which a proposal covers a GT box
    whole_objects : the RP gets ``predict.whole_objects``' gates (the first value of
        :func:`rescu.extension.predict.rp_gates`)

    Returns
    -------
    ``{stage: count}`` for :data:`STAGES`, each count <= the one before
    """
    from rescu.evaluation.metrics import iod_matrix
    from rescu.boxes import size_gate
    from rescu.extension.predict import proposal_gates

    out = dict.fromkeys(STAGES, 0)
    out["missing"] = len(missing)
    if not len(missing) or not len(boxes):
        return out
    cover = iod_matrix(boxes, missing) > h                       # (P, M)
    thr, ratio = proposal_gates(lattice, params, whole_objects)
    gates = [np.ones(len(boxes), bool),
             lattice if lattice_only else np.ones(len(boxes), bool),
             prob.argmax(1) == k + 1,
             prob[:, k + 1] >= thr,
             distance <= ratio * max(radius, 1e-6),
             size_gate(boxes, own, params.examples.size_tolerance)]
    ok = np.ones(len(boxes), bool)
    for stage, g in zip(STAGES[1:], gates):
        ok = ok & g
        out[stage] = int(cover[ok].any(0).sum())
    return out


def image_funnels(stage1: Any, stage2: Any, feats: dict[str, Any], ckpt: dict[str, Any],
                  gt_rps: Sequence[Sequence[Sequence[float]]], params: Any, h: float = 0.5
                  ) -> tuple[dict[str, int], dict[str, int]]:
    """:func:`gate_funnel` summed over one image's accepted RESCU-I RPs: (as configured,
    any proposal allowed), each with ``not extended`` and ``added`` counts."""
    from rescu.evaluation.metrics import iod_matrix, score_image
    from rescu.extension.examples import select_examples
    from rescu.extension.predict import rp_gates, score_proposals

    conf, anyp = dict.fromkeys(COUNTS, 0), dict.fromkeys(COUNTS, 0)
    det = [[i.bbox for i in p.instances] for p in stage1.patterns]
    if not det or not gt_rps:
        return conf, anyp
    assign = score_image(det, gt_rps, h).rp_assignment
    rp_index = [int(v) for v in np.asarray(feats["rp_index"]).reshape(-1)]
    boxes = np.asarray(feats["proposals"], float).reshape(-1, 4)
    lattice = np.asarray(feats.get("proposal_lattice", np.zeros(len(boxes)))).reshape(-1) > 0
    if len(lattice) != len(boxes):
        lattice = np.zeros(len(boxes), bool)
    trained = bool(rp_index) and bool(ckpt.get("state_dict"))
    prob = score_proposals(feats, ckpt) if trained and len(boxes) else None
    sel = select_examples(feats, params) if prob is not None else None
    new = np.array([i.bbox for p in stage2.patterns for i in p.instances
                    if i.source == "stage2"], float).reshape(-1, 4)
    for pi, g in enumerate(assign):
        if g is None:
            continue
        own = np.asarray(det[pi], float).reshape(-1, 4)
        G = np.asarray(gt_rps[g], float).reshape(-1, 4)
        missing = G[~(iod_matrix(own, G) > h).any(0)]
        if not len(missing):
            continue
        added = int((iod_matrix(new, missing) > h).any(0).sum()) if len(new) else 0
        if pi not in rp_index or prob is None:
            for d in (conf, anyp):
                d["missing"] += len(missing)
                d["not extended"] += len(missing)
                d["added"] += added
            continue
        k = rp_index.index(pi)
        whole, _, lattice_only = rp_gates(stage1.patterns[pi], params)
        for d, lo in ((conf, lattice_only), (anyp, False)):
            f = gate_funnel(missing, k, own, boxes, lattice, prob, sel["distance"][:, k],
                            float(sel["radius"][k]), params, lo, h, whole)
            for s in STAGES:
                d[s] += f[s]
            d["added"] += added
    return conf, anyp


def main(argv: list[str] | None = None) -> int:
    from _cli import inputs_present, run_dataset, run_parser

    from rescu import io
    from rescu.extension.params import Stage2Params
    from rescu.extension.train import load_checkpoint
    from rescu.io import load_coco_rps

    ap = run_parser(__doc__)
    ap.add_argument("--iod", type=float, default=0.5, help="IOD threshold h (default 0.5)")
    a = ap.parse_args(argv)
    cfg, data = run_dataset(ap, a)
    run = a.results / a.dataset
    if not inputs_present((data / "annotations.json", "ground truth"),
                          (run / "rescu-i", "RESCU-I results"),
                          (run / "rescu-ii", "RESCU-II results")):
        return 2
    params = Stage2Params.from_dict(cfg["stage2"])
    tot_c, tot_a = dict.fromkeys(COUNTS, 0), dict.fromkeys(COUNTS, 0)
    n = 0
    for f, gts in load_coco_rps(data / "annotations.json").items():
        stem = Path(f).stem
        paths = [run / "rescu-i" / f"{stem}.json", run / "rescu-ii" / f"{stem}.json",
                 run / "stage2" / f"{stem}.feats.h5", run / "stage2" / f"{stem}.head.h5"]
        if not all(p.is_file() for p in paths):
            print(f"{f}: no RESCU-I / RESCU-II result or stage-II artefacts, skipped",
                  file=sys.stderr)
            continue
        feats, _ = io.read_h5(paths[2])
        ckpt = load_checkpoint(paths[3]).get("head", {})
        c, an = image_funnels(io.read_result(paths[0]), io.read_result(paths[1]), feats,
                              ckpt, [g.boxes for g in gts], params, a.iod)
        for d, s in ((tot_c, c), (tot_a, an)):
            for key in COUNTS:
                d[key] += s[key]
        n += 1
    lo = params.predict.lattice_only
    print(f"## {a.dataset}: {n} images, GT instances of accepted RESCU-I RPs' GT RPs that "
          f"the RP misses (IOD > {a.iod})\n")
    print(f"| gate | as configured (lattice_only: {str(lo).lower()}) | any proposal |")
    print("|---|---:|---:|")
    for key in ("missing", "not extended") + STAGES[1:] + ("added",):
        print(f"| {key} | {tot_c[key]} | {tot_a[key]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
