"""What the speed scripts share: the photos they time (the first few of each set of
../shared/data, resized to a given number of megapixels) and the timing of one call."""

from __future__ import annotations

from pathlib import Path
import statistics
import time
from typing import Any, Callable, Sequence

import cv2
import numpy as np

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


def photos(sets: Sequence[str], per_set: int) -> list[Path]:
    """The first ``per_set`` JPEG / PNG files (by name) of ``SHARED/<set>/images`` for each
    set present; [] without ../shared/data."""
    out = []
    for s in sets:
        d = SHARED / s / "images"
        if d.is_dir():
            out += sorted(p for p in d.iterdir() if p.suffix.lower() in (".jpg", ".png"))[:per_set]
    return out


def resized(rgb: np.ndarray, megapixels: float) -> np.ndarray:
    """``rgb`` (H, W, 3) resized, aspect kept, to about ``megapixels`` million pixels."""
    h, w = rgb.shape[:2]
    s = (megapixels * 1e6 / (w * h)) ** 0.5
    return cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


def median_seconds(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """``(median wall seconds of repeats calls of fn, the last call's result)``."""
    runs, out = [], None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = fn()
        runs.append(time.perf_counter() - t)
    return statistics.median(runs), out
