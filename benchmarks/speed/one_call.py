"""Seconds a photo and peak memory of ``rescu discover`` on ten 1-MP photos in one call.

    python benchmarks/speed/one_call.py                  # ten photos of ../shared/data, 1 MP
    python benchmarks/speed/one_call.py --mp 12 --n 1    # one 12-MP photo
    python benchmarks/speed/one_call.py --photo a.jpg --photo b.jpg --method rescu-i

The measure of the camera-speed issue's bar: the photos (default: the first photo of each
of the nine sets of ``../shared/data``, then the second of the first sets until there are
``--n``; without ``../shared/data`` the package photos) resized to ``--mp`` megapixels
(aspect kept, PNG in a temporary folder) are given to **one** ``rescu discover`` call (the
installed command's code, run as ``python -m rescu.cli``: the process start, the imports,
the backbone's loading, the overlays and the gallery all count), and the script prints its
wall seconds over the number of photos and the peak resident memory of its process tree
(``ru_maxrss`` of the waited-for child: the CLI runs every photo itself, in one process, no
worker; this parent imports neither NumPy nor torch, and the child is a fresh ``exec``,
so the figure is the child's own). ``--repeat`` runs the call several times and prints
each and the median. Run it on an idle machine; it asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SETS = ("spb_facades", "cmp_facade", "chess", "york_urban", "aerial_cars", "parking_lot",
        "blood_cells", "nuclei", "aquarium")
PHOTO_EXT = (".jpg", ".jpeg", ".png")


def default_photos(n: int) -> list[Path]:
    """The first photo of each set of ``../shared/data`` present, then the second of each,
    ... until ``n``; the package photos when the folder is absent."""
    data = REPO.parent / "shared" / "data"
    per_set = [sorted(p for p in (data / s / "images").iterdir()
                      if p.suffix.lower() in PHOTO_EXT)
               for s in SETS if (data / s / "images").is_dir()]
    out: list[Path] = []
    k = 0
    while per_set and len(out) < n and any(k < len(x) for x in per_set):
        out += [x[k] for x in per_set if k < len(x)][:n - len(out)]
        k += 1
    if out:
        return out
    sys.path.insert(0, str(REPO))
    from rescu.data.photos import package_photo_dir  # noqa: PLC0415

    return sorted(package_photo_dir().glob("*.png"))[:n]


def resized(photo: Path, mp: float, folder: Path, k: int) -> Path:
    """``photo`` resized to about ``mp`` megapixels (aspect kept), as PNG in ``folder``
    (named with its position ``k``, so two photos of one name stay two)."""
    import cv2

    img = cv2.imread(str(photo), cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"{photo}: not readable")
    h, w = img.shape[:2]
    s = (mp * 1e6 / (w * h)) ** 0.5
    size = (max(16, round(w * s)), max(16, round(h * s)))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
    out = folder / f"{k:02d}_{photo.stem}.png"
    cv2.imwrite(str(out), img)
    return out


def one_call(paths: list[Path], out: Path, method: str, sets: list[str]) -> tuple[float, int]:
    """``(wall seconds, peak bytes)`` of one ``rescu discover`` call on ``paths``."""
    cmd = [sys.executable, "-m", "rescu.cli", "discover", *map(str, paths), "--out", str(out),
           "--method", method, "--quiet"] + [x for s in sets for x in ("--set", s)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if proc.returncode != 0:
        raise SystemExit(f"rescu discover failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    if peak <= before:
        print("note: the peak is no higher than an earlier call's (ru_maxrss is the largest "
              "child's so far)", file=sys.stderr)
    return wall, peak * 1024


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photo", action="append", type=Path, default=None)
    ap.add_argument("--n", type=int, default=10, help="photos (default 10)")
    ap.add_argument("--mp", type=float, default=1.0, help="megapixels (default 1)")
    ap.add_argument("--method", default="rescu-ii", choices=["rescu-ii", "rescu-i"])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override, as rescu discover --set")
    a = ap.parse_args(argv)
    photos = a.photo or default_photos(a.n)
    walls, peaks = [], []
    with tempfile.TemporaryDirectory() as tmp:
        paths = [resized(p, a.mp, Path(tmp), k) for k, p in enumerate(photos)]
        print(f"{len(paths)} photo(s) at {a.mp:g} MP: " + ", ".join(p.name for p in photos))
        for r in range(max(1, a.repeat)):
            wall, peak = one_call(paths, Path(tmp) / f"out{r}", a.method, a.sets)
            walls.append(wall / len(paths))
            peaks.append(peak)
            print(f"run {r + 1}: {wall:.1f} s in all, {wall / len(paths):.2f} s a photo, "
                  f"peak {peak / 2**20:.0f} MiB", flush=True)
    if len(walls) > 1:
        print(f"median: {statistics.median(walls):.2f} s a photo, peak "
              f"{statistics.median(peaks) / 2**20:.0f} MiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
