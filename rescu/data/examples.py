"""Example photos shipped with RESCU: real photos of recurring things, credited.

A dozen small photos from the openly licensed sets of the project's evaluation data
(blood cells, nuclei, a car park, aquarium tanks, facades, chess), with the sets' own
ground-truth boxes, live in the package folder ``rescu/data/examples/`` (``images/``,
``annotations.json``, ``CREDITS.md``): a run without any data of its own (the config's
dataset ``examples``, ``kind: examples``) then shows what RESCU finds on the kinds of
photos it is for, and scores it.

:func:`build_examples` makes that folder from the evaluation sets (a maintainer's step:
``python -m rescu.data.examples ../shared/data``); it picks the first
``per_set`` photos of each set in the order of its ``annotations.json`` (no choice by
result), shrinks each to at most ``max_side`` pixels on its longer side and scales its
boxes with it. Only the sets of :data:`LICENSED_SETS` may ship.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["LICENSED_SETS", "examples_dir", "build_examples"]

#: The sets whose photos may ship: name -> (source, licence, how to credit it).
LICENSED_SETS: dict[str, tuple[str, str]] = {
    "blood_cells": ("BCCD Dataset (Shenggan), https://github.com/Shenggan/BCCD_Dataset",
                    "MIT"),
    "nuclei": ("2018 Data Science Bowl stage 1 (BBBC038, Broad Bioimage Benchmark "
               "Collection, fixed masks), https://bbbc.broadinstitute.org/BBBC038", "CC0 1.0"),
    "parking_lot": ('Roboflow Universe "Cars - Overhead View" (AVDC_GDP_Cranfield_2023)',
                    "public domain"),
    "aquarium": ("Roboflow Aquarium dataset (underwater-object-detection repository), "
                 "credit Roboflow, https://public.roboflow.com/object-detection/aquarium",
                 "CC BY 4.0"),
    "spb_facades": ("building-facades-advertising-dataset (Urban Research Lab), "
                    "https://github.com/Urban-Research-Lab/building-facades-advertising-dataset",
                    "CC0 1.0"),
    "chess": ("Roboflow chess-0wzkb v7 (via bobroj/Robotic_Vision)", "CC BY 4.0"),
}


def examples_dir() -> Path:
    """The folder of the shipped example photos (``images/``, ``annotations.json``,
    ``CREDITS.md``) inside the installed package."""
    return Path(__file__).resolve().parent / "examples"


def build_examples(data_root: str | Path, out_dir: str | Path,
                   sets: tuple[str, ...] = tuple(LICENSED_SETS), per_set: int = 2,
                   max_side: int = 800, quality: int = 90) -> list[Path]:
    """Make the example folder from the evaluation sets.

    Parameters
    ----------
    data_root : path
        The folder of the sets (``../shared/data``), each ``<set>/images`` and
        ``<set>/annotations.json`` (COCO, as ``../shared/README.md``).
    out_dir : path
        Where ``images/<set>-<k>.jpg``, ``annotations.json`` and ``CREDITS.md`` go
        (written atomically; other files there are left alone).
    sets : tuple of str
        Names of :data:`LICENSED_SETS`.
    per_set : int
        The first this many images of each set (the order of its annotations).
    max_side : int
        Longer side at most this many pixels (boxes scaled alike).
    quality : int
        JPEG quality.

    Returns
    -------
    list of Path
        The written photos.

    Raises
    ------
    ValueError
        A set that may not ship (its licence does not allow it).
    FileNotFoundError
        A set's folder or annotations are missing.
    """
    import cv2

    from ..io import atomic_path

    def atomic_write_bytes(path: Path, data: bytes) -> None:
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)

    def atomic_write_text(path: Path, text: str) -> None:
        atomic_write_bytes(path, text.encode("utf-8"))

    bad = [s for s in sets if s not in LICENSED_SETS]
    if bad:
        raise ValueError(f"{bad}: only {sorted(LICENSED_SETS)} may ship (licences)")
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    coco: dict[str, Any] = {"info": {"about": "example photos shipped with RESCU; see "
                                     "CREDITS.md for each photo's source and licence"},
                            "images": [], "annotations": [], "categories": []}
    cats: dict[str, int] = {}
    credits = ["# Credits of the example photos", "",
               "Each photo is a resized copy (longer side at most "
               f"{max_side} pixels, JPEG quality {quality}) of a photo of an openly "
               "licensed dataset; its boxes are that dataset's own labels, scaled alike. "
               "Made by `python -m rescu.data.examples ../shared/data`.", "",
               "| photo | dataset | original file | source | licence |",
               "|---|---|---|---|---|"]
    written = []
    for name in sets:
        root = Path(data_root) / name
        ann = json.loads((root / "annotations.json").read_text())
        cat_name = {c["id"]: c["name"] for c in ann["categories"]}
        source, licence = LICENSED_SETS[name]
        for k, im in enumerate(ann["images"][:per_set], 1):
            img = cv2.imread(str(root / im["file_name"]), cv2.IMREAD_COLOR)
            if img is None:
                raise FileNotFoundError(f"{root / im['file_name']}: not a readable image")
            h, w = img.shape[:2]
            s = min(1.0, max_side / max(h, w))
            if s < 1.0:
                img = cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if not ok:
                raise ValueError(f"{root / im['file_name']}: could not encode it")
            fn = f"images/{name}-{k}.jpg"
            atomic_write_bytes(out / fn, buf.tobytes())
            written.append(out / fn)
            new_id = len(coco["images"]) + 1
            entry = {"id": new_id, "file_name": fn, "width": img.shape[1],
                     "height": img.shape[0], "dataset": name,
                     "source_file": im["file_name"]}
            if im.get("count_class"):
                entry["count_class"] = im["count_class"]
            coco["images"].append(entry)
            for a in ann["annotations"]:
                if a["image_id"] != im["id"]:
                    continue
                cname = cat_name[a["category_id"]]
                cid = cats.setdefault(cname, len(cats) + 1)
                coco["annotations"].append({
                    "id": len(coco["annotations"]) + 1, "image_id": new_id,
                    "category_id": cid, "bbox": [round(v * s, 2) for v in a["bbox"]]})
            credits.append(f"| `{fn}` | {name} | `{Path(im['file_name']).name}` | {source} | "
                           f"{licence} |")
    coco["categories"] = [{"id": i, "name": n} for n, i in cats.items()]
    atomic_write_text(out / "annotations.json", json.dumps(coco, indent=1) + "\n")
    atomic_write_text(out / "CREDITS.md", "\n".join(credits) + "\n")
    return written


def main(argv: list[str] | None = None) -> int:
    """``python -m rescu.data.examples DATA_ROOT [OUT_DIR]``: (re)make the examples."""
    args = sys.argv[1:] if argv is None else argv
    if not 1 <= len(args) <= 2:
        print("usage: python -m rescu.data.examples DATA_ROOT [OUT_DIR]", file=sys.stderr)
        return 2
    out = Path(args[1]) if len(args) == 2 else examples_dir()
    for p in build_examples(args[0], out):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
