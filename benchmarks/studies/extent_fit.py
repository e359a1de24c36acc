"""How well the extent step recovers whole objects from part-sized boxes, by the ring its
colour contrast compares each box with: the extent alone, on the ground truth's objects.

The dense source's blobs lie on objects but are often smaller than them (a coin's face,
a car's roof); the extent step (:func:`rescu.extension.contrast_extent.refine_extent`) gives all
of an RP's boxes one scale, aspect and shift, where the boxes' colour differs most from a
ring around them. Here every GT RP of every image (the boxes of one category, two or
more) stands in for an RP found on the right objects: its boxes are replaced by squares
of ``--start`` x their side (sqrt of the area), on the same centres, and the extent
(the config's ``dense.extent_scales``, ``extent_aspects``, ``extent_shifts``) is asked
to grow them back, once per ring width of ``--ring`` (with ``--edges W``, the score adds
W x :func:`rescu.extension.contrast_extent.edge_contrast`, ``dense.extent_edges``). Prints, per
dataset and ring, the
mean IoU of each box with its GT box (mean over the GT RPs), and that of the squares it
started from. The photo is resized to ``--side`` px on its longer side first (the
pipeline's prepared images are 960-1600 px). Asserts nothing.

The step is measured alone: the RP's boxes are centred on the objects here, and which
group becomes an RP (its confidence, computed on the grown boxes) is not measured.

Usage (from the repository root; ``--data`` holds one folder per dataset)::

    python benchmarks/studies/extent_fit.py --data ../shared/data --dataset chess \\
        --dataset aerial_cars --dataset cmp_facade --dataset spb_facades \\
        --ring 0.5 --ring 0.25 --start 0.5 --start 0.75
    python benchmarks/studies/extent_fit.py --data ../shared/data --dataset aerial_cars \
        --ring 0.5 --edges 1
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parents[2])]


def squares(gt: "np.ndarray", start: float) -> "np.ndarray":  # noqa: F821
    """Squares of ``start`` x each box's side (sqrt of its area) on the boxes' centres."""
    import numpy as np

    side = np.sqrt(gt[:, 2] * gt[:, 3]) * start
    c = gt[:, :2] + gt[:, 2:] / 2
    return np.c_[c - side[:, None] / 2, side, side]


def main(argv: list[str] | None = None) -> int:
    import cv2
    import numpy as np

    from rescu.boxes import iou_matrix
    from rescu.config import load_config
    from rescu.discovery.sources import DenseParams
    from rescu.extension.contrast_extent import colour_integrals, gradient_integral, refine_extent

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--dataset", action="append", required=True, help="repeatable")
    ap.add_argument("--ring", action="append", type=float, default=None,
                    help="ring width / box side (repeatable; default 0.5 and 0.25)")
    ap.add_argument("--start", action="append", type=float, default=None,
                    help="start squares' side / the GT box's (repeatable; default 0.5)")
    ap.add_argument("--side", type=int, default=1024, help="longer side of the photos, px")
    ap.add_argument("--edges", type=float, default=0.0,
                    help="weight of the edge contrast in the extent's score (default 0)")
    a = ap.parse_args(argv)
    rings, starts = a.ring or [0.5, 0.25], a.start or [0.5]
    if min(rings) <= 0 or min(starts) <= 0 or a.edges < 0:
        ap.error("--ring and --start must be > 0, --edges >= 0")
    p = DenseParams.from_dict(load_config(None, stage2=False)["dense"])
    for ds in a.dataset:
        ann_path = a.data / ds / "annotations.json"
        if not ann_path.is_file():
            print(f"{ann_path}: not found", file=sys.stderr)
            return 2
        coco = json.loads(ann_path.read_text())
        boxes: dict[int, dict[int, list]] = defaultdict(lambda: defaultdict(list))
        for an in coco["annotations"]:
            boxes[an["image_id"]][an["category_id"]].append(an["bbox"])
        fit: dict[tuple[float, object], list[float]] = defaultdict(list)
        n_images = 0
        for im in coco["images"]:
            path = a.data / ds / im["file_name"]
            if not path.is_file():
                path = a.data / ds / "images" / Path(im["file_name"]).name
            bgr = cv2.imread(str(path))
            if bgr is None:
                print(f"{path}: not readable, skipped", file=sys.stderr)
                continue
            rps = [np.asarray(v, float) for v in boxes[im["id"]].values() if len(v) >= 2]
            if not rps:
                continue
            n_images += 1
            k = a.side / max(bgr.shape[:2])
            rgb = cv2.cvtColor(cv2.resize(bgr, None, fx=k, fy=k, interpolation=cv2.INTER_AREA),
                               cv2.COLOR_BGR2RGB)
            ii = colour_integrals(rgb)
            grad = gradient_integral(rgb) if a.edges > 0 else None
            for gt in rps:
                gt = gt * k
                for s in starts:
                    sq = squares(gt, s)
                    fit[(s, "start")].append(float(np.diag(iou_matrix(sq, gt)).mean()))
                    for r in rings:
                        got, _ = refine_extent(rgb, sq, p.extent_scales, p.extent_aspects,
                                               p.extent_shifts, ii, ring=r, edges=a.edges,
                                               gradients=grad)
                        fit[(s, r)].append(float(np.diag(iou_matrix(got, gt)).mean()))
        n_rps = len(next(iter(fit.values()), []))
        print(f"\n{ds}: {n_images} images, {n_rps} GT RPs; mean IoU with the GT boxes"
              + (f" (edges {a.edges:g})" if a.edges else ""))
        for s in starts:
            row = "  ".join(f"ring {r}: {np.mean(fit[(s, r)]):.3f}" for r in rings)
            print(f"  start {s} (IoU {np.mean(fit[(s, 'start')]):.3f})  {row}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
