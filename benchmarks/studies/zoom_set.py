"""A zoomed copy of a labelled set: each photo cropped around its objects so that they
fill a larger share of the frame, with the ground truth cropped alike.

The real sets here show small objects (cars from above, chess pieces, windows: 2-6 % of
the photo's side); photos of a few large things (coins, cookies, fruit on a plate) are
not among them. Cropping a square around each photo's largest GT RP, of ``1 /
--share`` times its median object side, makes a set of the same real objects at about
``--share`` of the frame's side, with their labels, to measure how discovery behaves
with object size (the crop is not enlarged: the pipeline sees a smaller photo).

For each image: the largest GT RP (most boxes of one category), its median box side
``m``; a square crop of side ``m / share`` (at most the photo's shorter side) centred on
the GT box of that RP nearest to the RP's centroid, moved to lie inside the photo. Every
GT box with at least ``--keep`` of its area inside is kept, clipped to the crop; images
left with fewer than ``--min-objects`` boxes of that RP are skipped. Writes
``<out>/images/<stem>.png`` and ``<out>/annotations.json`` (COCO, the source's
categories) and refuses an ``out`` that already holds files. Asserts nothing.

Usage (from the repository root)::

    python benchmarks/studies/zoom_set.py ../shared/data/aerial_cars /tmp/zoom/aerial_cars
    rescu discover /tmp/zoom/aerial_cars --method rescu-i --out /tmp/zoom-out/aerial_cars
    python benchmarks/studies/compare_folders.py /tmp/zoom/aerial_cars \\
        default=/tmp/zoom-out/aerial_cars
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1])]


def crop_window(boxes: "list[list[float]]", width: int, height: int, share: float
                ) -> tuple[int, int, int] | None:
    """``(x0, y0, side)`` of the square crop around ``boxes`` (one GT RP, ``[x, y, w, h]``
    pixels) in a ``width x height`` photo, or None for an empty RP."""
    import numpy as np

    b = np.asarray(boxes, float).reshape(-1, 4)
    if not len(b):
        return None
    m = float(np.median(np.sqrt(b[:, 2] * b[:, 3])))
    side = int(min(round(m / share), width, height))
    c = b[:, :2] + b[:, 2:] / 2
    k = int(np.argmin(((c - c.mean(0)) ** 2).sum(1)))
    x0 = int(np.clip(round(c[k, 0] - side / 2), 0, width - side))
    y0 = int(np.clip(round(c[k, 1] - side / 2), 0, height - side))
    return x0, y0, side


def main(argv: list[str] | None = None) -> int:
    import cv2
    import numpy as np

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="labelled set (annotations.json, images/)")
    ap.add_argument("out", type=Path, help="new folder for the zoomed set")
    ap.add_argument("--share", type=float, default=0.15,
                    help="median object side / crop side (default 0.15)")
    ap.add_argument("--keep", type=float, default=0.8,
                    help="a GT box is kept with at least this share of its area inside")
    ap.add_argument("--min-objects", type=int, default=3,
                    help="least boxes of the largest GT RP in a crop")
    a = ap.parse_args(argv)
    if not 0 < a.share < 1:
        ap.error(f"--share must be in (0, 1), got {a.share}")
    if a.out.exists() and any(a.out.iterdir()):
        print(f"{a.out}: exists and is not empty; give a new folder", file=sys.stderr)
        return 2
    coco = json.loads((a.data / "annotations.json").read_text())
    anns = defaultdict(list)
    for an in coco["annotations"]:
        anns[an["image_id"]].append(an)
    (a.out / "images").mkdir(parents=True, exist_ok=True)
    images, annotations, skipped = [], [], 0
    for im in coco["images"]:
        bgr = cv2.imread(str(a.data / im["file_name"]), cv2.IMREAD_COLOR)
        if bgr is None:
            print(f"{im['file_name']}: cannot be read, skipped", file=sys.stderr)
            skipped += 1
            continue
        H, W = bgr.shape[:2]
        by_cat = defaultdict(list)
        for an in anns[im["id"]]:
            by_cat[an["category_id"]].append(an)
        if not by_cat:
            skipped += 1
            continue
        cat, largest = max(by_cat.items(), key=lambda kv: (len(kv[1]), -kv[0]))
        win = crop_window([an["bbox"] for an in largest], W, H, a.share)
        if win is None:
            skipped += 1
            continue
        x0, y0, side = win
        kept = []
        for an in anns[im["id"]]:
            x, y, w, h = an["bbox"]
            cx0, cy0 = max(x, x0), max(y, y0)
            cx1, cy1 = min(x + w, x0 + side), min(y + h, y0 + side)
            if cx1 <= cx0 or cy1 <= cy0 or (cx1 - cx0) * (cy1 - cy0) < a.keep * w * h:
                continue
            kept.append({**an, "bbox": [cx0 - x0, cy0 - y0, cx1 - cx0, cy1 - cy0]})
        if sum(an["category_id"] == cat for an in kept) < a.min_objects:
            skipped += 1
            continue
        name = f"images/{Path(im['file_name']).stem}.png"
        if not cv2.imwrite(str(a.out / name), bgr[y0:y0 + side, x0:x0 + side]):
            raise OSError(f"{a.out / name}: could not be written")
        images.append({"id": im["id"], "file_name": name, "width": side, "height": side})
        annotations += [{**an, "area": float(an["bbox"][2] * an["bbox"][3])} for an in kept]
    out = {"info": {"description": f"zoomed copy of {a.data.name} (share {a.share})"},
           "images": images, "annotations": annotations,
           "categories": coco.get("categories", [])}
    tmp = a.out / "annotations.json.tmp"
    tmp.write_text(json.dumps(out))
    tmp.replace(a.out / "annotations.json")
    sides = [im["width"] for im in images]
    print(f"{a.out}: {len(images)} images ({skipped} skipped), {len(annotations)} boxes; "
          f"crop side median {int(np.median(sides)) if sides else 0} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
