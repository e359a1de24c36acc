"""What the scene step (RP-based VPs, translation symmetry, dominant RP) costs on a run.

Usage::

    python benchmarks/speed/scene_cost.py RESULTS_DIR --dataset york_urban [--set KEY=VALUE ...]

Times :func:`rescu.scene.analyse.analyse_scene` (the default ``scene`` section, each
``--set`` a ``scene.vp`` key, e.g. ``hidden_rows=false``) on every RESCU-II result of the
dataset in a finished run (``RESULTS_DIR/<dataset>/rescu-ii/*.json``), in one process,
one thread (a scene job also starts Python: ``step_imports.py``). Prints the number of
images, the mean, median and largest seconds per image, and how many of the images have
stage-I RPs hidden by the confidence (the rows ``scene.vp.hidden_rows`` reads).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402

sys.path[:0] = [str(Path(__file__).resolve().parents[2])]

from rescu import io  # noqa: E402
from rescu.config import load_config  # noqa: E402
from rescu.scene.analyse import SceneParams, analyse_scene, hidden_patterns  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene.vp setting (repeatable), e.g. hidden_rows=false")
    a = ap.parse_args(argv)
    section = load_config(None)["scene"]
    vp = dict(section["vp"])
    for kv in a.set:
        key, sep, value = kv.partition("=")
        if not sep:
            ap.error(f"--set {kv!r}: expected KEY=VALUE")
        vp[key] = yaml.safe_load(value)
    try:
        params = SceneParams.from_config(dict(section, vp=vp))
    except ValueError as e:
        ap.error(str(e))
    files = sorted((a.results / a.dataset / "rescu-ii").glob("*.json"))
    if not files:
        ap.error(f"no RESCU-II results in {a.results / a.dataset / 'rescu-ii'}")
    seconds, with_hidden = [], 0
    for f in files:
        res = io.read_result(str(f))
        with_hidden += bool(hidden_patterns(res))
        t = time.perf_counter()
        analyse_scene(res, params)
        seconds.append(time.perf_counter() - t)
    s = np.array(seconds)
    print(f"{a.dataset}: {len(s)} images ({with_hidden} with hidden stage-I RPs), scene step "
          f"mean {s.mean():.3f} s, median {np.median(s):.3f} s, max {s.max():.3f} s"
          + (f" ({', '.join(a.set)})" if a.set else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
