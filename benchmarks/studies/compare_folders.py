"""Per-image RP results of two or more folders (runs, methods, versions) side by side.

Prints the RP table's metrics (the paper's instance precision / recall, RP precision /
recall and the any-RP instance figures; mean ± std over the images that have a result in
every folder) of each folder, and with exactly two folders the paired Wilcoxon p-value of
each metric; then, per folder, the dominant RP (the most confident) against the image's
largest GT RP: the share of its objects covered, the dominant RP's precision on them and
its count's mean relative error (and the share of images within 35 %), over the images
with a result in that folder. Use it for a before / after of two pipeline runs on the
same images. Asserts nothing.

Usage (from the repository root)::

    python benchmarks/studies/compare_folders.py ../shared/data/aerial_cars \\
        before=<run A>/aerial_cars/rescu-ii after=<run B>/aerial_cars/rescu-ii
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parents[2]),
                str(Path(__file__).resolve().parents[1]), str(Path(__file__).resolve().parent)]


def main(argv: list[str] | None = None) -> int:
    from _cli import print_side_by_side

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="dataset folder (annotations.json)")
    ap.add_argument("folders", nargs="+", metavar="LABEL=FOLDER",
                    help="per-image JSON folders, each with its row label")
    a = ap.parse_args(argv)
    folders: dict[str, Path] = {}
    for item in a.folders:
        label, sep, folder = item.partition("=")
        if not sep or not label or not folder:
            ap.error(f"{item!r}: expected LABEL=FOLDER")
        if label in folders:
            ap.error(f"label {label!r} given twice")
        folders[label] = Path(folder)
    for path in [a.data / "annotations.json", *folders.values()]:
        if not path.exists():
            print(f"{path}: not found", file=sys.stderr)
            return 2
    print_side_by_side(a.data, folders, a.data.name)
    print_dominant(a.data, folders)
    return 0


def print_dominant(data: Path, folders: dict[str, Path]) -> None:
    """Per folder: the dominant RP against the largest GT RP (covered / precision /
    mean relative count error, share within 35 %; :func:`rp_sources.dominant_summary`)."""
    from rp_sources import dominant_summary, rp_rows

    print("\ndominant RP vs the largest GT RP: covered / precision / count error (within 35 %)")
    for label, folder in folders.items():
        d = dominant_summary(rp_rows(data, folder)[1])
        if d is None:
            print(f"  {label}: no image with a GT RP")
            continue
        print(f"  {label}: {d['covered']:.3f} / {d['precision']:.3f} / "
              f"{d['count_error']:.2f} ({d['within_35']:.2f}), {d['images']} images")

if __name__ == "__main__":
    raise SystemExit(main())
