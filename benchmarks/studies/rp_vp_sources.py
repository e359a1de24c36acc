"""Study: which RPs the RP-only vanishing point is computed from, on a finished run.

Usage::

    python benchmarks/studies/rp_vp_sources.py RESULTS_DIR [--dataset york_urban]

For every image of the dataset with ground-truth VPs, the scene step
(:func:`rescu.core.analyse_scene`, the default ``scene`` section) runs again on the
run's RESCU-II result (``rescu-ii/<image>.json``) with these sets of RPs:

* ``reported``: the result's RPs (what the run's scene step used);
* ``reported + hidden stage I``: also the stage-I RPs the confidence hid
  (``candidate_patterns`` dropped for ``"low confidence"``, not extended by stage II);
* ``hidden only with a reported RP``: the same on the images with a reported RP, none
  on the others;
* ``reported, else hidden``: the reported RPs' VP, and where they give none the VP of
  the reported and the hidden stage-I RPs together;
* ``stage I only``: the reported and the hidden stage-I RPs, no dense RP;
* ``reported, no dense``: the reported stage-I RPs alone.

Prints per variant the share of images with a VP, the share within 5 degrees of the closest
GT VP (the dataset's focal length where it gives one, else the nominal) and the median
error: how much of the RP-only VP's change under the whole-objects default comes from the
hidden stage-I RPs and how much from the dense ones. Asserts nothing.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2])]

VARIANTS = ("reported", "reported + hidden stage I", "hidden only with a reported RP",
            "reported, else hidden", "stage I only", "reported, no dense")


def _patterns(d: dict[str, Any], variant: str) -> list[dict[str, Any]]:
    """The RP JSONs of one variant of the result JSON ``d``."""
    rep = d["patterns"]
    hidden = [c for c in d.get("candidate_patterns", [])
              if c.get("dropped") == "low confidence" and c.get("source") != "dense"]
    if variant == "reported":
        return rep
    if variant == "reported + hidden stage I":
        return rep + hidden
    if variant == "hidden only with a reported RP":
        return rep + hidden if rep else []
    if variant == "stage I only":
        return [p for p in rep if p.get("source") != "dense"] + hidden
    return [p for p in rep if p.get("source") != "dense"]


def main(argv: list[str] | None = None) -> int:
    import argparse

    from rescu import core, io
    from rescu.config import load_config
    from rescu.evaluation.vpd import _camera, load_vanishing_points
    from rescu.scene.vp.errors import closest_gt_error
    from rescu.types import ImageResult

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", default="york_urban")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"),
                    help="the datasets' folder (default ../shared/data)")
    a = ap.parse_args(argv)
    cfg = load_config(None)
    root = a.data / a.dataset
    truth = load_vanishing_points(root / "vanishing_points.json")
    errors: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for name, g in sorted(truth.items()):
        src = a.results / a.dataset / "rescu-ii" / f"{Path(name).stem}.json"
        if not g["vanishing_points"] or not src.is_file():
            continue
        d = io.read_json(src)
        prep = core.prepare_file(str(root / name), **{
            k: cfg["image"][k] for k in ("max_side", "min_side", "max_pixels")})
        size, focal, pp, _ = _camera(g)
        vps = {}
        for v in VARIANTS:
            if v == "reported, else hidden":
                vp = vps["reported"] or vps["reported + hidden stage I"]
            else:
                dd = copy.deepcopy(d)
                dd["patterns"] = [dict(p, id=k) for k, p in enumerate(_patterns(d, v))]
                dd["candidate_patterns"] = []
                res = ImageResult.from_json(dd)
                out, _ = core.analyse_scene(prep, res, cfg["scene"])
                vp = vps[v] = out.vanishing_point
            errors[v].append(float("inf") if vp is None else closest_gt_error(
                vp.homogeneous, g["vanishing_points"], "vector", size, focal, pp))
    print(f"{a.dataset}: RP-only VP from each set of RPs (images, with a VP, within 5 deg, "
          "median deg)")
    for v, e in errors.items():
        x = np.array(e, float)
        if not len(x):
            continue
        print(f"  {v:<26} {len(x):>4}  {np.isfinite(x).mean():.2f}  {(x <= 5).mean():.2f}  "
              f"{np.median(x):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
