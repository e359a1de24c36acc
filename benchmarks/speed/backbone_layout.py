"""What the backbone's memory layout costs: channels-first (NCHW) against channels-last
(NHWC) weights and inputs, on the passes the pipeline makes.

Usage::

    python benchmarks/speed/backbone_layout.py [--repeats 5] [--threads 1]

Times, for EfficientNet-Lite0 (:class:`rescu.extension.backbone.FrozenBackbone`) with
each layout: the dense step's stride-8 + stride-16 maps of a 1.2-MP and a 4.3-MP image
(its coarse and fine levels), stage II's stride-16 map of a 0.8-MP image, and the
classifier on a batch of six 160-pixel crops (the dense step's objectness). The image is
the first CMP facade of ../shared/data when present, a rendered texture otherwise.
Prints per pass the median seconds of each layout, their ratio, and the largest absolute
difference between the two layouts' outputs (the maps: feature units; the classifier:
probability). ``--threads``: torch threads (the pipeline's backbone jobs use 1).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _photos import median_seconds, photos  # noqa: E402


def test_image() -> np.ndarray:
    """(H, W, 3) uint8: the first CMP facade, or a rendered texture without ../shared/data."""
    found = photos(["cmp_facade"], 1)
    if found:
        return cv2.cvtColor(cv2.imread(str(found[0])), cv2.COLOR_BGR2RGB)
    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    return cv2.resize(small, (1024, 768), interpolation=cv2.INTER_CUBIC)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    import torch

    from rescu.extension.backbone import FrozenBackbone

    torch.set_num_threads(a.threads)
    rgb = test_image()

    def at(side: int) -> np.ndarray:
        s = side / max(rgb.shape[:2])
        return cv2.resize(rgb, None, fx=s, fy=s, interpolation=cv2.INTER_AREA if s < 1
                          else cv2.INTER_LINEAR)

    crops = np.stack([cv2.resize(rgb[i * 40:i * 40 + 120, i * 60:i * 60 + 120], (160, 160))
                      for i in range(6)])
    passes: dict[str, Callable[[Any], list[np.ndarray]]] = {
        "dense coarse maps 1280 px": lambda b, im=at(1280): [
            t.numpy() for t in b.multiscale_maps(im)],
        "dense fine maps 2400 px": lambda b, im=at(2400): [
            t.numpy() for t in b.multiscale_maps(im)],
        "stage II map 1024 px": lambda b, im=at(1024): [b.feature_map(im).numpy()],
        "objectness 6 x 160 px": lambda b: [b.class_probabilities(crops)],
    }
    channels_last = FrozenBackbone("efficientnet-lite0", feature_stride=16)
    channels_first = FrozenBackbone("efficientnet-lite0", feature_stride=16)
    channels_first.model = channels_first.model.to(memory_format=torch.contiguous_format)
    prep = channels_first.preprocess
    channels_first.preprocess = lambda im: prep(im).contiguous()  # type: ignore[method-assign]
    print(f"EfficientNet-Lite0, {a.threads} torch thread(s), median of {a.repeats}:")
    print(f"  {'pass':28s} {'NCHW s':>8s} {'NHWC s':>8s} {'ratio':>6s} {'max diff':>9s}")
    for name, fn in passes.items():
        fn(channels_first), fn(channels_last)  # warm-up: allocations, kernel choice
        t_first, out_first = median_seconds(lambda: fn(channels_first), a.repeats)
        t_last, out_last = median_seconds(lambda: fn(channels_last), a.repeats)
        diff = max(float(np.abs(np.asarray(x) - np.asarray(y)).max())
                   for x, y in zip(out_first, out_last))
        print(f"  {name:28s} {t_first:8.3f} {t_last:8.3f} {t_first / t_last:6.2f} "
              f"{diff:9.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
