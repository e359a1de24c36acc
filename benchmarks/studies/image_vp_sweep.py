"""Study: the image's joint VP estimator under other settings, on a finished run's results.

Usage::

    python benchmarks/studies/image_vp_sweep.py RESULTS_DIR [--datasets synthetic york_urban]
        [--set rp_weight=4 --set inlier_angle_deg=1.5 ...] [--true-focal]

For every image of each dataset in RESULTS_DIR (its ``prepared/`` image and ``scene/``
JSON, as the pipeline wrote them) the joint estimator
(:func:`rescu.scene.image_vp.image_vanishing_points`) runs again with the default
``scene.image_vp`` section changed by ``--set key=value`` (numbers, true / false), and
prints per dataset: images, share of images whose dominant VP is within 5 degrees of a
GT VP, the median of that error, and AA@10 of the dominant VP and of the triplet (true
focal where the dataset gives it; :mod:`rescu.evaluation.vpd`). ``--true-focal`` gives
the estimator the dataset's focal length.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

from rescu import io
from rescu.data.datasets import rectified_vp_truth
from rescu.evaluation.vpd import angular_accuracy
from rescu.params import config_defaults
from rescu.pipeline import read_prepared
from rescu.scene.analyse import SceneParams
from rescu.scene.image_vp import image_vanishing_points
from rescu.scene.vp.errors import vector_error
from rescu.scene.vp.manhattan import ImageVPParams


def truth_of(results: Path, ds: str) -> dict:
    cfg = config_defaults("datasets").get(ds, {})
    for p in (results / ds / "vanishing_points.json",
              Path(cfg.get("path", "/nonexistent")) / "vanishing_points.json",
              results / "data" / "synthetic" / "vanishing_points.json"):
        if p.is_file() and (ds == "synthetic") == ("synthetic" in str(p)):
            return io.load_vanishing_points(p)
    if cfg.get("vp_truth") == "rectified":
        t = rectified_vp_truth(io.read_json(Path(cfg["path"]) / "annotations.json"))
        tmp = results / f".{ds}-vp-truth.json"
        tmp.write_text(json.dumps(t))
        return io.load_vanishing_points(tmp)
    raise SystemExit(f"no VP ground truth for {ds}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--datasets", nargs="+", default=["synthetic", "york_urban"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--true-focal", action="store_true")
    a = ap.parse_args(argv)
    over = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)}
    params = ImageVPParams.from_dict({**config_defaults("scene", "image_vp"), **over})
    scene = SceneParams.from_config(config_defaults("scene"))
    print(f"settings: {over or 'defaults'}{' (true focal given)' if a.true_focal else ''}")
    for ds in a.datasets:
        gt = truth_of(a.results, ds)
        dom, tri = [], []
        for sj in sorted((a.results / ds / "scene").glob("*.json")):
            src = io.read_result(sj)
            g = gt.get(src.image)
            if g is None or not g["vanishing_points"]:
                continue
            pre = a.results / ds / "prepared"
            rgb, meta = read_prepared(str(pre / f"{sj.stem}.png"), str(pre / f"{sj.stem}.meta.json"))
            f_true = g.get("focal_px")
            res = image_vanishing_points(rgb, float(meta["scale_factor"]), src, scene, params,
                                         f_true if a.true_focal else None)
            size = (g["width"], g["height"])
            err = lambda v, q: vector_error(np.asarray(v, float), q, size, f_true,  # noqa: E731
                                            g.get("principal_point"))
            listed = [v["homogeneous"] for v in res.extra["vanishing_points"]]
            if not listed and res.vanishing_point is not None:
                listed = [res.vanishing_point.homogeneous]
            vp = res.vanishing_point
            dom.append(min(err(vp.homogeneous, q) for q in g["vanishing_points"])
                       if vp is not None else np.inf)
            tri += [min((err(v, q) for v in listed), default=np.inf)
                    for q in g["vanishing_points"]]
        d = np.array(dom)
        print(f"{ds:<12} images {len(d):>3}  dominant <=5 deg {np.mean(d <= 5):.3f}  "
              f"median {np.median(d):.2f} deg  AA@10 dominant {angular_accuracy(d, 10):.3f}  "
              f"triplet {angular_accuracy(tri, 10):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
