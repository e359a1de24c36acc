"""When does the angular constraint (AC) matter? VP success with and without it, against
the RANSAC hypothesis budget.

The pipeline's VP tables compare RESCU with and without AC at the config's budget
(``scene.vp.ransac_iterations``). An RP has few implicit lines, so that budget usually
covers *every* pair of lines: the near-parallel pairs the AC refuses are hypothesised
too, but a hypothesis from two near-parallel lines rarely has the most inliers, and the
refinement that follows starts from the best one. This script measures the AC where it
is meant to help: when only a few random pairs can be drawn.

For each image of each dataset, the scene step's input (``<results>/<dataset>/<source>/``,
the config's ``scene.source``) is completed once, as the pipeline does
(:func:`rescu.completion.complete_rows`), then :func:`rescu.scene.analyse_scene` runs
with ``vp.ransac_iterations`` in ``--budgets`` and ``vp.ac_threshold_deg`` at the
config's value and at 0 (off), for each of ``--seeds`` RANSAC seeds; with ``--lsd`` the
explicit-line baseline (:func:`rescu.vp.line_vanishing_point`) runs under the same
variants. The image VP is compared with the closest ground-truth VP (vector error in
degrees, true focal length where the dataset has one, as the VP tables do; a missing VP
is a failure). Prints, per dataset, method, budget and AC: the success rate at each
``--deg`` threshold and the median error, both averaged over the seeds, and the
paired Wilcoxon p-value of AC against no AC over all images x seeds.

Usage (after ``snakemake --cores 2``, from the repository root)::

    python benchmarks/studies/vp_ac_sweep.py results
    python benchmarks/studies/vp_ac_sweep.py results --datasets synthetic --budgets 5 10 1000 --lsd
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's rescu package

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402


def sweep(results: Path, cfg: dict[str, Any], datasets: Sequence[str],
          budgets: Sequence[int], seeds: int, lsd: bool = False) -> pd.DataFrame:
    """One VP error per dataset x image x method x budget x seed x AC.

    Parameters
    ----------
    results : Path
        Results folder of a finished run.
    cfg : dict
        The run's config (:func:`rescu.config.load_config`).
    datasets : names in ``cfg["datasets"]``
        Those without ``vanishing_points.json`` or scene input are skipped (a message).
    budgets : ints >= 1
        Values of ``vp.ransac_iterations``.
    seeds : int >= 1
        RANSAC seeds ``vp.seed + 0 .. seeds - 1`` (the config's seed first).
    lsd : bool
        Also the LSD-line baseline.

    Returns
    -------
    DataFrame
        ``dataset, image, method ("RESCU" | "LSD lines"), budget, seed, ac (bool),
        err`` (vector error to the closest GT VP, degrees; inf = no VP).
    """
    import cv2

    from rescu.scene import completion as CO
    from rescu import io
    from rescu.scene import analyse as SC
    from rescu.scene.vp.errors import closest_gt_error
    from rescu.scene.vp.lsd import line_vanishing_point
    from rescu.data.datasets import dataset_root
    from rescu.io import load_vanishing_points
    from rescu.pipeline import read_prepared

    base = SC.SceneParams.from_config(cfg["scene"])
    cp = CO.CompletionParams.from_dict(cfg["scene"].get("completion") or {})
    ac_on = float(base.vp.ac_threshold_deg)
    rows = []
    for dsn in datasets:
        data = dataset_root(dsn, cfg["datasets"][dsn], str(results))
        gt_path = data / "vanishing_points.json"
        src = results / dsn / cfg["scene"]["source"]
        if not gt_path.exists() or not src.is_dir():
            print(f"{dsn}: skipped ({gt_path} or {src} missing)", file=sys.stderr)
            continue
        gt = load_vanishing_points(gt_path)
        prep = results / dsn / "prepared"
        for f, g in gt.items():
            stem = Path(f).stem
            if not g["vanishing_points"] or not (src / f"{stem}.json").exists():
                continue
            res = io.read_result(src / f"{stem}.json")
            w, h = g["width"], g["height"]
            focal = float(g["focal_px"]) if g.get("focal_px") is not None else (w + h) / 4.0
            pp = (g["principal_point"] if g.get("principal_point") is not None
                  else (w / 2.0, h / 2.0))

            def err(vp: Any) -> float:
                if vp is None:
                    return float("inf")
                return closest_gt_error(vp.homogeneous, g["vanishing_points"], "vector",
                                          (w, h), focal, pp)

            failed = bool(res.extra.get("failure"))
            if not failed:
                rgb, _ = read_prepared(str(prep / f"{stem}.png"),
                                       str(prep / f"{stem}.meta.json"))
                sf = float(io.read_json(prep / f"{stem}.meta.json")["scale_factor"])
                done = CO.complete_rows(res, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cp,
                                        scale_factor=sf, vp_params=base.vp)
            for budget in budgets:
                for seed in range(base.vp.seed, base.vp.seed + seeds):
                    for ac in (ac_on, 0.0):
                        vpp = dataclasses.replace(base.vp, ransac_iterations=int(budget),
                                                  seed=seed, ac_threshold_deg=ac)
                        key = {"dataset": dsn, "image": f, "budget": int(budget),
                               "seed": seed, "ac": ac > 0}
                        vp = (None if failed else SC.analyse_scene(
                            done, dataclasses.replace(base, vp=vpp)).vanishing_point)
                        rows.append({**key, "method": "RESCU", "err": err(vp)})
                        if lsd:
                            lv = None if failed else line_vanishing_point(
                                rgb, vpp, scale_factor=sf)
                            rows.append({**key, "method": "LSD lines", "err": err(lv)})
    return pd.DataFrame(rows, columns=["dataset", "image", "budget", "seed", "ac", "method",
                                       "err"])


def summarise(df: pd.DataFrame, deg: Sequence[float]) -> pd.DataFrame:
    """Per dataset x method x budget x AC: success rate at each threshold in ``deg`` and
    the median error (degrees), each averaged over the seeds, and the paired Wilcoxon
    p-value of AC on against off over all images x seeds (:func:`rescu.vp.paired_test`)."""
    from rescu.evaluation.vpd import paired_test

    out = []
    for (dsn, m, b), g in df.groupby(["dataset", "method", "budget"], sort=False):
        piv = g.pivot_table(index=["image", "seed"], columns="ac", values="err")
        p = paired_test(piv[True].to_numpy(), piv[False].to_numpy())
        for ac in (True, False):
            ga = g[g["ac"] == ac]
            r: dict[str, Any] = {"dataset": dsn, "method": m, "budget": b,
                                 "AC": "on" if ac else "off",
                                 "n_images": ga["image"].nunique()}
            per_seed = ga.groupby("seed")["err"]
            for t in deg:
                r[f"success@{t:g}deg"] = float(per_seed.apply(
                    lambda e, t=t: np.mean(e <= t)).mean())
            r["median_err_deg"] = float(per_seed.median().mean())
            r["p_ac_vs_off"] = p
            out.append(r)
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    from rescu.config import load_config

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--datasets", nargs="+", default=["synthetic", "york_urban"])
    ap.add_argument("--budgets", nargs="+", type=int, default=[5, 10, 25, 100, 1000],
                    help="values of scene.vp.ransac_iterations")
    ap.add_argument("--seeds", type=int, default=5, help="RANSAC seeds per variant")
    ap.add_argument("--deg", nargs="+", type=float, default=[2.0, 5.0])
    ap.add_argument("--lsd", action="store_true", help="also the LSD-line baseline")
    ap.add_argument("--config", type=Path, default=None,
                    help="config file merged over the defaults (rescu/defaults/config.yaml)")
    a = ap.parse_args(argv)
    if min(a.budgets) < 1 or a.seeds < 1:
        ap.error("--budgets and --seeds must be at least 1")
    cfg = load_config(a.config)
    if float(cfg["scene"]["vp"]["ac_threshold_deg"]) == 0:
        ap.error("the config's scene.vp.ac_threshold_deg is 0: nothing to compare")
    unknown = [d for d in a.datasets if d not in cfg["datasets"]]
    if unknown:
        ap.error(f"dataset {unknown[0]!r} is not in the config ({', '.join(cfg['datasets'])})")
    t0 = time.perf_counter()
    df = sweep(a.results, cfg, a.datasets, a.budgets, a.seeds, a.lsd)
    if df.empty:
        print(f"{a.results}: no image with a ground-truth VP and a scene input "
              "(run the pipeline first)", file=sys.stderr)
        return 2
    with pd.option_context("display.width", 250, "display.max_rows", None):
        print(summarise(df, a.deg).round(3).to_string(index=False))
    print(f"({len(df)} VP estimates, {a.seeds} seeds, {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
