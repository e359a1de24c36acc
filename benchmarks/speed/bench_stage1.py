"""Speed and memory of stage I (RESCU-I and GRASP).

Usage::

    python benchmarks/speed/bench_stage1.py [--image PATH] [--megapixels 0.3 1 3]
        [--grasp-keypoints 1000] [--repeats 3] [--grasp-memory] [--skip-grasp]

For an image resized to each size: seconds and tracemalloc peak (MiB) of SIFT
extraction, affinity precomputation (correspondences + URP table), one search, the
full adaptive grid (``discover`` over the 45 parameter sets, which share their
searches) and GRASP; then the time of ``discover`` against the number of keypoints
with a fitted exponent (t ~ K^a); then GRASP against RESCU-I at the same keypoint
budget, timed back to back in this process (perf_counter only, no tracemalloc, whose
overhead differs between the two), ``--repeats`` times. The default image is the first of ../shared/data/cmp_facade, or a synthetic
grid when that is absent. Single-threaded.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rescu.discovery.features import FeatureParams, extract_features  # noqa: E402
from rescu.discovery.grasp import GraspParams, discover_grasp  # noqa: E402
from rescu.discovery.search import search  # noqa: E402
from rescu.discovery.stage1 import (Stage1Params, discover, precompute_urps,  # noqa: E402
                                    search_context)
from rescu.discovery.urp import Gates  # noqa: E402

cv2.setNumThreads(1)
SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


def measure(fn):
    tracemalloc.start()
    t = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak / 2**20


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def base_image(path: str | None) -> np.ndarray:
    if path is None:
        cand = SHARED / "cmp_facade" / "images"
        if cand.is_dir():
            path = str(sorted(cand.iterdir())[0])
    if path is not None:
        from rescu.io import load_image
        return load_image(path, max_side=10000).rgb
    rng = np.random.default_rng(0)
    tile = cv2.resize(rng.integers(0, 256, (10, 10)).astype(np.uint8), (60, 60),
                      interpolation=cv2.INTER_NEAREST)
    img = np.full((1000, 1000), 120, np.uint8)
    for y in range(20, 940, 100):
        for x in range(20, 940, 100):
            img[y:y + 60, x:x + 60] = tile
    return np.dstack([img] * 3)


def resize_to(img: np.ndarray, mp: float) -> np.ndarray:
    h, w = img.shape[:2]
    s = np.sqrt(mp * 1e6 / (h * w))
    return cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))),
                      interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image")
    ap.add_argument("--megapixels", nargs="+", type=float, default=[0.3, 1.0, 3.0])
    ap.add_argument("--grasp-keypoints", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3,
                    help="back-to-back GRASP / RESCU-I timings at --grasp-keypoints")
    ap.add_argument("--grasp-memory", action="store_true",
                    help="also one tracemalloc run of GRASP (slow)")
    ap.add_argument("--skip-grasp", action="store_true")
    a = ap.parse_args(argv)
    base = base_image(a.image)
    p = Stage1Params()
    print(f"{'MP':>5}{'K':>6}{'sift s':>9}{'MiB':>7}{'affin s':>9}{'MiB':>7}"
          f"{'1 search s':>11}{'grid+disc s':>12}{'MiB':>7}{'fixed s':>9}{'x SIFT':>8}")
    one_mp = None
    for mp in a.megapixels:
        img = resize_to(base, mp)
        f, t_sift, m_sift = measure(lambda: extract_features(img, FeatureParams(upsample_below=0)))
        diag = float(np.hypot(*f.image_size))

        def aff():
            ctx, d = search_context(f, p)
            return ctx, precompute_urps(ctx, 0.2 * d, p.spatial_k, p.pos_tol)
        (ctx, table), t_aff, m_aff = measure(aff)
        g = Gates(p.P_d * diag, p.P_s, p.P_theta)
        seeds = table.seeds(g)
        if len(seeds):
            _, t_one, _ = measure(lambda: search(ctx, seeds[0], np.ones(len(f), bool), g))
        else:
            t_one = float("nan")
        _, t_full, m_full = measure(lambda: discover(f, p))
        _, t_fixed, _ = measure(lambda: discover(f, Stage1Params(adaptive=())))
        print(f"{img.shape[0] * img.shape[1] / 1e6:>5.2f}{len(f):>6}{t_sift:>9.3f}{m_sift:>7.1f}"
              f"{t_aff:>9.3f}{m_aff:>7.1f}{t_one:>11.4f}{t_full:>12.3f}{m_full:>7.1f}"
              f"{t_fixed:>9.3f}{t_full / t_sift:>8.1f}", flush=True)
        if abs(mp - 1.0) < 1e-9:
            one_mp = img
    img = one_mp if one_mp is not None else resize_to(base, 1.0)
    print("\ntime of discover (full grid) vs keypoints, ~1 MP image")
    ks, ts = [], []
    for n in (500, 1000, 2000, 4000):
        f = extract_features(img, FeatureParams(n_features=n, upsample_below=0))
        _, t, _ = measure(lambda: discover(f, p))
        ks.append(len(f))
        ts.append(t)
        print(f"  K={len(f):>5}  {t:.3f} s", flush=True)
    if len(set(ks)) > 1:
        slope = np.polyfit(np.log(ks), np.log(ts), 1)[0]
        print(f"  fitted exponent a (t ~ K^a): {slope:.2f}")
    if not a.skip_grasp:
        f = extract_features(img, FeatureParams(n_features=a.grasp_keypoints, upsample_below=0))
        print(f"\nGRASP vs RESCU-I at K={len(f)} (back to back, {a.repeats} repeats)")
        ratios = []
        for _ in range(a.repeats):
            t_r = timed(lambda: discover(f, p))
            t_rf = timed(lambda: discover(f, Stage1Params(adaptive=())))
            t_g = timed(lambda: discover_grasp(f, GraspParams()))
            ratios.append(t_g / t_r)
            print(f"  GRASP {t_g:.3f} s, RESCU-I full grid {t_r:.3f} s (x{t_g / t_r:.1f}), "
                  f"RESCU-I fixed params {t_rf:.3f} s (x{t_g / t_rf:.1f})", flush=True)
        print(f"  GRASP / RESCU-I (full grid): median x{np.median(ratios):.1f}, "
              f"min x{min(ratios):.1f}")
        if a.grasp_memory:
            _, _, m_g = measure(lambda: discover_grasp(f, GraspParams()))
            print(f"  GRASP tracemalloc peak {m_g:.1f} MiB")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak RSS of the process: {rss:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
