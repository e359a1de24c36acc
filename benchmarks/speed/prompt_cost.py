"""Seconds per photo of "count these" (one example box) against the unprompted default.

Usage (from the repository root)::

    python benchmarks/speed/prompt_cost.py                     # 2 photos of each box set
    python benchmarks/speed/prompt_cost.py --per-set 4 --set nuclei --set chess

For the first ``--per-set`` photos of each dataset (``../shared/data/<set>``), times
:func:`rescu.core.run_image` on the photo file twice in one process: the default
(RESCU-II, no examples) and with the counted class's median-area box as the example
(``benchmarks/count_these.py``'s choice; the default ``prompt.unprompted: false``, so
nothing else is looked for). A warm-up photo first, so the backbone's loading and the
imports count in neither. Prints per set and overall the mean seconds per photo of each
and their ratio; asserts nothing. The thread count is the config's (``threads``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def main(argv: list[str] | None = None) -> int:
    from count_these import BOX_SETS, counted_boxes, example_boxes

    from rescu import core
    from rescu.config import load_config
    from rescu.io import load_coco_rps

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--set", dest="sets", action="append", default=None)
    ap.add_argument("--per-set", type=int, default=2)
    a = ap.parse_args(argv)
    cfg = load_config(None)
    rows = []
    warm = False
    for name in a.sets or BOX_SETS:
        ann = a.data / name / "annotations.json"
        if not ann.is_file():
            print(f"{name}: no {ann}, skipped", file=sys.stderr)
            continue
        gts = load_coco_rps(ann)
        images = {im["file_name"]: im for im in json.loads(ann.read_text())["images"]}
        files = [f for f in gts if gts[f]][:a.per_set]
        for fn in files:
            ex = example_boxes(counted_boxes(images, gts[fn], fn), 1)
            path = a.data / name / fn
            if not warm:
                core.run_image(path, cfg)
                core.run_image(path, cfg, examples=ex)
                warm = True
            t0 = time.perf_counter()
            core.run_image(path, cfg)
            t1 = time.perf_counter()
            core.run_image(path, cfg, examples=ex)
            t2 = time.perf_counter()
            rows.append((name, t1 - t0, t2 - t1))
        mine = [r for r in rows if r[0] == name]
        if mine:
            d, p = np.mean([r[1] for r in mine]), np.mean([r[2] for r in mine])
            print(f"{name:14s} photos {len(mine):3d}  default {d:6.2f} s  one example "
                  f"{p:6.2f} s  ratio {p / d:.3f}", flush=True)
    if rows:
        d, p = np.mean([r[1] for r in rows]), np.mean([r[2] for r in rows])
        print(f"{'ALL':14s} photos {len(rows):3d}  default {d:6.2f} s  one example "
              f"{p:6.2f} s  ratio {p / d:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
