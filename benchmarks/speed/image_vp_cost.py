"""What the image's joint VP estimator (RP rows + LSD lines, Manhattan triplet) costs.

Usage::

    python benchmarks/speed/image_vp_cost.py [--megapixels 1.0] [--per-set 4] [--repeats 3]

Takes the first ``--per-set`` photos of each set of ../shared/data (York Urban, CMP
facades, SPb facades, chess, aerial cars; a synthetic rendering when absent), resizes
each to ``--megapixels`` and times :func:`rescu.scene.image_vp.image_vanishing_points`
(LSD, hypotheses over the focal grid, refinement; the focal estimated, no RP rows: the
RP lines are few next to the segments) ``--repeats`` times. Prints per image the median
seconds and the number of segments, then the median and maximum over images.
Single-threaded, as one pipeline job.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _photos import median_seconds, photos, resized  # noqa: E402

from rescu.scene.image_vp import image_vanishing_points  # noqa: E402
from rescu.scene.vp.lsd import lsd_segments  # noqa: E402
from rescu.scene.vp.params import VPParams  # noqa: E402
from rescu.types import ImageResult  # noqa: E402

cv2.setNumThreads(1)
SETS = ["york_urban", "cmp_facade", "spb_facades", "chess", "aerial_cars"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--megapixels", type=float, default=1.0)
    ap.add_argument("--per-set", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    paths = photos(SETS, a.per_set)
    if not paths:
        print("no ../shared/data: a synthetic rendering stands in", file=sys.stderr)
        img = np.full((600, 800, 3), 200, np.uint8)
        rng = np.random.default_rng(0)
        for _ in range(300):
            x, y = rng.integers(0, 800), rng.integers(0, 600)
            cv2.line(img, (int(x), int(y)), (int(x + rng.integers(-80, 80)), int(y)), (0, 0, 0), 2)
        images = [("synthetic", img)]
    else:
        images = [(p.parent.parent.name + "/" + p.name,
                   cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)) for p in paths]
    vpp = VPParams()
    times = []
    print(f"{'image':<40} {'size':>11} {'segments':>8} {'seconds':>8}")
    for name, rgb in images:
        rgb = resized(rgb, a.megapixels)
        h, w = rgb.shape[:2]
        src = ImageResult(image=name, width=w, height=h, method="rescu-ii")
        n_seg = len(lsd_segments(rgb, vpp.lsd_min_length * float(np.hypot(w, h)),
                                 vpp.lsd_max_segments))
        times.append(median_seconds(lambda: image_vanishing_points(rgb, 1.0, src),
                                    a.repeats)[0])
        print(f"{name:<40} {w:>5}x{h:<5} {n_seg:>8} {times[-1]:>8.3f}")
    print(f"\n{len(times)} images at {a.megapixels:g} MP: median {statistics.median(times):.3f} s, "
          f"max {max(times):.3f} s per image (median of {a.repeats} runs each)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
