"""Whole-image cost of RESCU-II against RESCU-I: ``rescu discover`` as whole processes.

    python benchmarks/speed/stage2_cost.py [IMAGE ...] [--repeat 3] [--data ../shared/data]

Without images, takes the first image of each ``../shared/data`` set (five sets: facades,
street facades, chess, aerial cars, York Urban). For every image, ``--repeat``
interleaved pairs of ``rescu discover --method rescu-i`` and ``--method rescu-ii`` (each a
new process, imports included, as a user runs it), in a temporary output folder. Prints
per image the median wall seconds and CPU seconds (user + system of the process) of each
method and their ratio, then the median ratio over images. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RESCU = Path(sys.executable).parent / "rescu"
SETS = ("cmp_facade", "spb_facades", "chess", "aerial_cars", "york_urban")


def first_images(data: Path) -> list[Path]:
    out = []
    for s in SETS:
        imgs = sorted((data / s / "images").glob("*"))
        if imgs:
            out.append(imgs[0])
    return out


def run_once(image: Path, method: str) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of one ``rescu discover`` process."""
    with tempfile.TemporaryDirectory(prefix="rescu-cost-") as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run([str(RESCU), "discover", str(image), "--out", out, "--quiet",
                               "--method", method], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode not in (0, 1):
        sys.exit(f"rescu discover failed on {image}:\n{proc.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("images", nargs="*", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="interleaved pairs per image")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    a = ap.parse_args(argv)
    if a.repeat < 1:
        ap.error("--repeat must be >= 1")
    images = a.images or first_images(a.data)
    if not images:
        ap.error(f"no images given and none found under {a.data}")
    ratios_wall, ratios_cpu = [], []
    print(f"{'image':<34} {'I wall':>7} {'I cpu':>7} {'II wall':>8} {'II cpu':>7} "
          f"{'x wall':>7} {'x cpu':>6}")
    for img in images:
        runs: dict[str, list[tuple[float, float]]] = {"rescu-i": [], "rescu-ii": []}
        for _ in range(a.repeat):
            for m in runs:
                runs[m].append(run_once(img, m))
        med = {m: (statistics.median(w for w, _ in r), statistics.median(c for _, c in r))
               for m, r in runs.items()}
        rw = med["rescu-ii"][0] / med["rescu-i"][0]
        rc = med["rescu-ii"][1] / med["rescu-i"][1]
        ratios_wall.append(rw)
        ratios_cpu.append(rc)
        print(f"{img.parent.parent.name + '/' + img.name:<34.34} {med['rescu-i'][0]:7.2f} "
              f"{med['rescu-i'][1]:7.2f} {med['rescu-ii'][0]:8.2f} {med['rescu-ii'][1]:7.2f} "
              f"{rw:7.2f} {rc:6.2f}")
    print(f"median RESCU-II / RESCU-I over {len(images)} images: wall "
          f"{statistics.median(ratios_wall):.2f}x, CPU {statistics.median(ratios_cpu):.2f}x")


if __name__ == "__main__":
    main()
