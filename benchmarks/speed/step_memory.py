"""Peak memory and wall time of the pipeline's two backbone steps, one process each.

    python benchmarks/speed/step_memory.py RESULTS [--dataset SET ...] [--retain BYTES]
    python benchmarks/speed/step_memory.py RESULTS --python OTHER_VENV/bin/python

For the first prepared image of each dataset of a finished run (``RESULTS``, e.g.
``results/realdev`` or ``results/paper``; default: the four real RP sets), runs the
``dense`` step (:func:`rescu.pipeline.dense`) and the ``stage2_features`` step
(:func:`rescu.pipeline.stage2_features` then :func:`rescu.pipeline.stage2_train`) each in a
new process, as the pipeline's jobs do (the default config, one backbone thread), writing
into a temporary folder, and prints each process's wall seconds and peak resident memory
(``ru_maxrss``). Run it on an idle machine.

``--python``: the interpreter of another environment (this repository's code first on its
path), e.g. one with the PyTorch CPU wheel, to compare with this environment's torch build;
where that environment has no torchvision, RoI align runs as
:func:`rescu.extension.backbone.roi_align_torch` (torchvision's sampling in plain torch),
as the library does there. ``--retain``: the limit given to
:func:`rescu.core.retain_freed_memory` (0: the C library's own behaviour).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SETS = ("cmp_facade", "spb_facades", "aerial_cars", "chess")

CHILD = r'''
import resource, sys, tempfile, time
t0 = time.perf_counter()
res, ds, im, step, limit = sys.argv[1:6]
limit = int(limit)
import yaml
import rescu.core as core
if limit == 0:
    core.retain_freed_memory = lambda limit=0: False
else:
    core.retain_freed_memory.__defaults__ = (limit,)
import torch
from rescu import pipeline
import rescu.extension.backbone as B
has_op = B._roi_align() is not B.roi_align_torch
cfg = yaml.safe_load(open("rescu/defaults/config.yaml"))
out = tempfile.mkdtemp(prefix="rescu-stepmem-")
p = f"{res}/{ds}/prepared/{im}"
core.limit_threads(cfg["threads"]["stage2_features"], torch=True)
if step == "dense":
    d = {**cfg["dense"], "enabled": True, "mode": "both", "confidence_stage1_score_scale": 0.0}
    pipeline.dense(p + ".png", p + ".meta.json", out + "/d.json", d, out + "/m.h5")
else:
    s2 = {k: v for k, v in cfg["stage2"].items() if k != "predict"}
    st1 = f"{res}/{ds}/rescu-i/{im}.json"
    pipeline.stage2_features(p + ".png", p + ".meta.json", st1, out + "/f.h5", s2)
    core.limit_threads(cfg["threads"]["stage2_head"])
    pipeline.stage2_train(out + "/f.h5", st1, out + "/h.h5", s2)
print(f"{time.perf_counter() - t0:.2f} {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.3f}"
      f" {torch.__version__} {'torchvision' if has_op else 'plain-roi-align'}")
'''


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run")
    ap.add_argument("--dataset", action="append", default=[], help=f"repeatable; default {SETS}")
    ap.add_argument("--python", default=sys.executable, help="interpreter of the environment to measure")
    ap.add_argument("--retain", type=int, default=1 << 30,
                    help="retain_freed_memory's limit in bytes (0: not called)")
    a = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    res = a.results.resolve()
    print(f"{'dataset/image':44s} {'step':6s} {'wall s':>7s} {'peak GB':>8s}  torch")
    for ds in a.dataset or SETS:
        stage1 = sorted((res / ds / "rescu-i").glob("*.json"))
        if not stage1:
            print(f"{ds}: no RESCU-I results in {res / ds}, skipped")
            continue
        im = stage1[0].stem
        for step in ("dense", "stage2"):
            r = subprocess.run([a.python, "-c", CHILD, str(res), ds, im, step, str(a.retain)],
                               cwd=REPO, env=env, capture_output=True, text=True)
            if r.returncode:
                print(f"{ds}/{im} {step}: failed\n{r.stderr[-2000:]}")
                return 1
            wall, peak, version, roi = r.stdout.split()[-4:]
            print(f"{ds + '/' + im:44s} {step:6s} {float(wall):7.2f} {float(peak):8.3f}  {version} ({roi})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
