"""What each per-image step of the pipeline spends importing, as its job does.

    python benchmarks/speed/step_imports.py RESULTS [--dataset SET] [--repeats 3]

For the first prepared image of ``--dataset`` (default ``cmp_facade``) of a finished run
(``RESULTS``, e.g. ``results/realdev``), runs each per-image step (SIFT features, the
dense step, RESCU-I, GRASP, stage II's features and head, stage II's prediction) in a new
process under ``python -X importtime``, as the pipeline's job does (the default config,
the pipeline's thread counts), writing into a temporary folder. Prints per step the
median over ``--repeats`` of the process's wall seconds and of the seconds spent in
imports (every top-level import, those made inside the step's functions included), and
the three top-level modules that cost most. A Snakemake job adds about 0.2-0.3 s of its
own (``job_overhead.py``). Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
STEPS = ("features", "dense", "rescu_i", "grasp", "stage2", "predict")

CHILD = r'''
import sys, tempfile, time
t0 = time.perf_counter()
res, ds, im, step, out = sys.argv[1:6]
from rescu import pipeline
from rescu.params import config_defaults
cfg = config_defaults()
th = cfg["threads"]
p, r = f"{res}/{ds}/prepared/{im}", f"{res}/{ds}"
if step == "features":
    pipeline.limit_threads(1)
    pipeline.features(p + ".png", p + ".meta.json", out + "/f.h5", cfg["features"])
elif step == "dense":
    pipeline.limit_threads(th["stage2_features"], torch=True)
    d = {**cfg["dense"], "enabled": True, "mode": "both", "confidence_stage1_score_scale": 0.0,
         "min_separation": -2.0, "min_object_separation": -2.0}
    pipeline.dense(p + ".png", p + ".meta.json", out + "/d.json", d, out + "/m.h5")
elif step == "rescu_i":
    pipeline.limit_threads(1)
    pipeline.stage1(f"{r}/features/{im}.h5", p + ".meta.json", out + "/s.json", out + "/s.h5",
                    cfg["stage1"], method="rescu-i", png=p + ".png",
                    dense_json=f"{r}/dense/{im}.json", dense_params=cfg["dense"],
                    dense_map_h5=f"{r}/dense/{im}.map.h5")
elif step == "grasp":
    pipeline.limit_threads(1)
    pipeline.stage1(f"{r}/features/{im}.h5", p + ".meta.json", out + "/g.json", out + "/g.h5",
                    cfg["grasp"], method="grasp")
elif step == "stage2":
    s2 = {k: v for k, v in cfg["stage2"].items() if k != "predict"}
    pipeline.limit_threads(th["stage2_features"], torch=True)
    pipeline.stage2_features(p + ".png", p + ".meta.json", f"{r}/rescu-i/{im}.json",
                             out + "/f2.h5", s2)
    pipeline.limit_threads(th["stage2_head"])
    pipeline.stage2_train(out + "/f2.h5", f"{r}/rescu-i/{im}.json", out + "/h.h5", s2)
else:
    pipeline.limit_threads(th["stage2_head"])
    pipeline.stage2_predict(f"{r}/stage2/{im}.feats.h5", f"{r}/stage2/{im}.head.h5",
                            f"{r}/rescu-i/{im}.json", out + "/p.json", p + ".meta.json",
                            cfg["stage2"])
print(f"WALL {time.perf_counter() - t0:.3f}")
'''

# "import time: self [us] | cumulative | <indent>name"
LINE = re.compile(r"^import time:\s+\d+ \|\s+(\d+) \| ( *)(\S+)")


def parse(stderr: str) -> tuple[float, dict[str, float]]:
    """Total seconds of top-level imports and the seconds of each top-level module."""
    top: dict[str, float] = {}
    for line in stderr.splitlines():
        m = LINE.match(line)
        if m and not m.group(2):
            top[m.group(3)] = top.get(m.group(3), 0.0) + int(m.group(1)) / 1e6
    return sum(top.values()), top


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", default="cmp_facade")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated, of {STEPS}")
    a = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    res = a.results.resolve()
    heads = sorted((res / a.dataset / "stage2").glob("*.head.h5"))
    if not heads:
        print(f"{res / a.dataset}: no stage-II head (a finished run with stage II?)")
        return 1
    im = heads[0].name[: -len(".head.h5")]
    print(f"{a.dataset}/{im}, median of {a.repeats}, python -X importtime")
    print(f"{'step':10s} {'wall s':>7s} {'imports s':>9s}  top-level imports (s)")
    for step in a.steps.split(","):
        walls, imps, tops = [], [], []
        for _ in range(a.repeats):
            with tempfile.TemporaryDirectory(prefix="rescu-imports-") as out:
                r = subprocess.run([sys.executable, "-X", "importtime", "-c", CHILD, str(res),
                                    a.dataset, im, step, out],
                                   cwd=REPO, env=env, capture_output=True, text=True)
            wall = re.search(r"WALL ([\d.]+)", r.stdout)
            if r.returncode or wall is None:
                print(f"{step}: failed\n{r.stderr[-2000:]}")
                return 1
            total, top = parse(r.stderr)
            walls.append(float(wall.group(1)))
            imps.append(total)
            tops.append(top)
        top = tops[imps.index(statistics.median_low(imps))]
        worst = ", ".join(f"{k} {v:.2f}" for k, v in
                          sorted(top.items(), key=lambda kv: -kv[1])[:3])
        print(f"{step:10s} {statistics.median(walls):7.2f} {statistics.median(imps):9.2f}  {worst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
