"""Study: the RP-only image VP under other settings, on a finished run's scene results.

Usage::

    python benchmarks/studies/rp_image_vp.py RESULTS_DIR
        [--datasets york_urban cmp_facade synthetic] [--set union_rows=false ...]
        [--weights track|count|one]

For every image of each dataset in RESULTS_DIR that has ground-truth VPs, the image VP
of the scene step (:func:`rescu.scene.analyse.image_rp_vp`) is computed again from the
analysed patterns of its ``scene/`` JSON (and the hidden stage-I RPs it keeps) with the
default ``scene.vp`` section changed by ``--set key=value``, and prints per dataset:
images, share with a VP, share within 5 degrees of the closest GT VP (angle error with
the dataset's focal length where it gives one, else the nominal), median error. ``--weights`` changes the vote of each implicit
line in the union of all patterns' rows (:func:`rescu.scene.vp.estimator.union_vanishing_point`):
its track length (the default), its pattern's instance count, or 1.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

from image_vp_sweep import truth_of
from rescu import io
from rescu.evaluation.vpd import _camera
from rescu.params import config_defaults
from rescu.scene.analyse import SceneParams, image_rp_vp
from rescu.scene.vp.errors import closest_gt_error


def image_vp(src, params: SceneParams, weights: str):
    """The RP-only image VP of one analysed result under ``params`` and ``weights``
    (with ``vp.hidden_rows``, the rows of the stage-I RPs the confidence hid too)."""
    votes = None if weights == "track" else (
        lambda p, lines: np.full(len(lines), float(p.count) if weights == "count" else 1.0))
    return image_rp_vp(src, params, votes)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--datasets", nargs="+", default=["york_urban", "cmp_facade", "synthetic"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--weights", choices=["track", "count", "one"], default="track")
    a = ap.parse_args(argv)
    over = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)}
    cfg = config_defaults("scene")
    params = SceneParams.from_config({**cfg, "vp": {**cfg["vp"], **over}})
    print(f"settings: {over or 'defaults'}, votes: {a.weights}")
    for ds in a.datasets:
        gt = truth_of(a.results, ds)
        errs = []
        for sj in sorted((a.results / ds / "scene").glob("*.json")):
            src = io.read_result(sj)
            g = gt.get(src.image)
            if g is None or not g["vanishing_points"]:
                continue
            size, focal, pp, _ = _camera(g)
            vp = image_vp(src, params, a.weights)
            errs.append(np.inf if vp is None else closest_gt_error(
                np.asarray(vp.homogeneous, float), g["vanishing_points"], "vector", size,
                focal, pp))
        e = np.array(errs)
        print(f"{ds:<12} images {len(e):>3}  has a VP {np.mean(np.isfinite(e)):.3f}  "
              f"<=5 deg {np.mean(e <= 5):.3f}  median {np.median(e):.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
