"""What the backbone's inference form buys: the published EfficientNet-Lite0
(channels-first memory, batch norms and padding as layers) against RESCU's (channels-last
weights and inputs, batch norms folded into the convolutions, stride-1 padding done by the
convolutions, activations in place), on the passes the pipeline makes.

Usage::

    python benchmarks/speed/backbone_layout.py [--repeats 5] [--threads 1]

Times, for each form of :class:`rescu.extension.backbone.FrozenBackbone`: the dense step's stride-8 + stride-16 maps of a 1.2-MP and a 4.3-MP image
(its coarse and fine levels), stage II's stride-16 map of a 0.8-MP image, and the
classifier on a batch of six 160-pixel crops (the dense step's objectness; it classifies
four per group by default now, but the batch stays six so that the figures compare with
those recorded before). The image is
the first CMP facade of ../shared/data when present, a rendered texture otherwise.
Prints per pass the median seconds of each form, their ratio, and the largest absolute
difference between their outputs relative to the published form's largest (the maps) or
absolute (the classifier's probabilities). ``--threads``: torch threads (the pipeline's backbone jobs use 1).
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
    ours = FrozenBackbone("efficientnet-lite0", feature_stride=16)
    # the published form: norms as layers
    published = FrozenBackbone("efficientnet-lite0", feature_stride=16, fuse=False)
    published.model = published.model.to(memory_format=torch.contiguous_format)
    prep = published.preprocess
    published.preprocess = lambda im: prep(im).contiguous()  # type: ignore[method-assign]
    print(f"EfficientNet-Lite0, {a.threads} torch thread(s), median of {a.repeats}:")
    print(f"  {'pass':28s} {'published s':>11s} {'rescu s':>8s} {'ratio':>6s} {'diff':>8s}")
    for name, fn in passes.items():
        fn(published), fn(ours)  # warm-up: allocations, kernel choice
        t_pub, out_pub = median_seconds(lambda: fn(published), a.repeats)
        t_ours, out_ours = median_seconds(lambda: fn(ours), a.repeats)
        scale = 1.0 if name.startswith("objectness") else max(
            float(np.abs(y).max()) for y in out_pub)
        diff = max(float(np.abs(np.asarray(x) - np.asarray(y)).max())
                   for x, y in zip(out_ours, out_pub)) / scale
        print(f"  {name:28s} {t_pub:11.3f} {t_ours:8.3f} {t_pub / t_ours:6.2f} {diff:8.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
