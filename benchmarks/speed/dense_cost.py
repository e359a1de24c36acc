"""What the dense RP source (rescu.extension.dense.find_dense) costs per image.

Usage::

    python benchmarks/speed/dense_cost.py [--megapixels 1.0] [--per-set 4] [--repeats 3] [--threads 2]
                                          [--strip-px N] [--rotations R] [--completion-turn]
                                          [--wide-scales YAML] [--against KEY=VALUE ...]

Takes the first ``--per-set`` photos of each set of ../shared/data (CMP and SPb facades,
chess, aerial cars; a synthetic rendering when absent), resizes each to
``--megapixels`` and times :func:`rescu.extension.dense.find_dense` (backbone pass,
centre-surround blobs, grouping, ranking) ``--repeats`` times with the default
``dense`` section, the backbone loaded once beforehand (as the pipeline's job loads it
once). Prints per image the median seconds and the number of dense RPs, then the
median and maximum over images, and the process's peak memory. ``--threads``: torch and
OpenCV threads (the pipeline's job: ``threads.stage2_features``, 1; ``rescu discover``:
``threads.in_process``, 2). ``--strip-px``: the backbone's first blocks run on strips of
inputs over this many pixels (:data:`rescu.extension.backbone.STRIP_PX`; 0: never, one
whole pass). ``--rotations``: ``dense.rotations`` instead of the config's (backbone
passes per map). ``--completion-turn``: ``dense.completion_turn`` on (one more backbone
pass per map that has a group to complete). ``--wide-scales``: ``dense.wide_scales``
instead of the config's (``[]``: no wide maps). ``--against``: a variant of the
``dense`` section (``KEY=VALUE``, the value read as YAML; repeatable, all keys in one
variant), timed on each image beside the settings above, the two alternating call by call
(which goes first alternates too), so that a change of the machine's speed during the run
falls on both alike; prints both medians per image, their sums and the variant's share.
The map cache of :func:`rescu.extension.dense.dense_map` is emptied before each call, so
every repeat passes the backbone.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _photos import median_seconds, photos, resized  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _cli import parse_sets  # noqa: E402

SETS = ["cmp_facade", "spb_facades", "chess", "aerial_cars"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--megapixels", type=float, default=1.0)
    ap.add_argument("--per-set", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--strip-px", type=int, default=None)
    ap.add_argument("--rotations", type=int, default=None,
                    help="dense.rotations (default: the config's)")
    ap.add_argument("--completion-turn", action="store_true",
                    help="dense.completion_turn on (default: the config's)")
    ap.add_argument("--wide-scales", default=None,
                    help="dense.wide_scales as YAML, e.g. '[]' for no wide maps "
                         "(default: the config's)")
    ap.add_argument("--against", action="append", default=[], metavar="KEY=VALUE",
                    help="time a variant of the dense section beside the settings, "
                         "alternating (repeatable: one variant of all the keys)")
    a = ap.parse_args(argv)
    try:
        against = parse_sets(a.against)
    except ValueError as e:
        ap.error(str(e))
    import torch

    import resource

    from rescu.discovery.sources import DenseParams
    from rescu.extension import backbone as B
    from rescu.extension import dense as D
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.dense import find_dense

    if a.strip_px is not None:
        B.STRIP_PX = a.strip_px if a.strip_px > 0 else 1 << 62

    def run(rgb: np.ndarray, params: DenseParams, backbone: FrozenBackbone):
        D._LAST_MAP.clear()
        return find_dense(rgb, params, backbone)

    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    paths = photos(SETS, a.per_set)
    if not paths:
        print("no ../shared/data: a synthetic rendering stands in", file=sys.stderr)
        rng = np.random.default_rng(0)
        img = np.clip(150 + rng.normal(0, 8, (800, 1200, 3)), 0, 255).astype(np.uint8)
        for i in range(40):
            x, y = int(rng.integers(20, 1150)), int(rng.integers(20, 750))
            cv2.circle(img, (x, y), 15, (200, 30, 30), -1)
        images = [("synthetic", img)]
    else:
        images = [(p.parent.parent.name + "/" + p.name,
                   cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)) for p in paths]
    over: dict = {}  # the settings: the default dense parameters with these options
    if a.rotations is not None:
        over["rotations"] = a.rotations
    if a.completion_turn:
        over["completion_turn"] = True
    if a.wide_scales is not None:
        import yaml

        over["wide_scales"] = yaml.safe_load(a.wide_scales)
    params = DenseParams.from_dict(over)
    variant = None
    if against:
        try:
            variant = DenseParams.from_dict({**over, **against})
        except (TypeError, ValueError) as e:
            ap.error(f"--against: {e}")
    backbone = FrozenBackbone(params.backbone, feature_stride=16)
    find_dense(np.zeros((64, 64, 3), np.uint8), params, backbone)   # warm-up
    if variant is not None:
        return _paired(images, params, variant, backbone, run, a, against)
    times = []
    print(f"{'image':<48} {'size':>11} {'RPs':>4} {'seconds':>8}")
    for name, rgb in images:
        rgb = resized(rgb, a.megapixels)
        h, w = rgb.shape[:2]
        med, found = median_seconds(lambda: run(rgb, params, backbone), a.repeats)
        times.append(med)
        print(f"{name:<48} {w:>5}x{h:<5} {len(found):>4} {med:>8.2f}")
    print(f"median {statistics.median(times):.2f} s, max {max(times):.2f} s over {len(times)} "
          f"image(s) at {a.megapixels} MP, {a.threads} thread(s); peak memory "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB, strips of "
          f"{B.STRIP_PX if B.STRIP_PX < 1 << 62 else 'no'} px, rotations {params.rotations}, "
          f"completion turned {params.completion_turn}, wide maps {list(params.wide_scales)}")
    return 0


def _paired(images, params, variant, backbone, run, a, against) -> int:
    """``--against``: each image timed with ``params`` and ``variant`` in turn."""
    import time

    sums = [0.0, 0.0]
    print(f"{'image':<48} {'size':>11} {'RPs':>9} {'seconds':>8} {'variant':>8}")
    for name, rgb in images:
        rgb = resized(rgb, a.megapixels)
        h, w = rgb.shape[:2]
        runs: list[list[float]] = [[], []]
        found: list = [None, None]
        for r in range(max(1, a.repeats)):
            for k in ((0, 1) if r % 2 == 0 else (1, 0)):
                t = time.perf_counter()
                found[k] = run(rgb, (params, variant)[k], backbone)
                runs[k].append(time.perf_counter() - t)
        med = [statistics.median(x) for x in runs]
        sums = [sums[0] + med[0], sums[1] + med[1]]
        print(f"{name:<48} {w:>5}x{h:<5} {len(found[0]):>4}/{len(found[1]):<4} "
              f"{med[0]:>8.2f} {med[1]:>8.2f}")
    print(f"sum {sums[0]:.1f} s, variant {sums[1]:.1f} s ({sums[1] / max(sums[0], 1e-9):.3f} of "
          f"it) over {len(images)} image(s) at {a.megapixels} MP, {a.threads} thread(s); "
          f"variant: {', '.join(f'{k}={v}' for k, v in against.items())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
