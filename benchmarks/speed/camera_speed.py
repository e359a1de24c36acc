"""Seconds of each stage and peak memory of the default discovery, by photo size.

    python benchmarks/speed/camera_speed.py                       # 0.25, 1, 4, 12 MP
    python benchmarks/speed/camera_speed.py --mp 1 --photo my.jpg --method rescu-i
    python benchmarks/speed/camera_speed.py --mp 1 --method rescu-i --set dense.enabled=false

For each photo (default: the first photo of ``../shared/data/spb_facades`` and of
``../shared/data/blood_cells`` when present, else the package photos ``brick.png`` and
``coins.png``) resized to each size in ``--mp`` (megapixels, aspect kept; written as PNG
into a temporary folder), runs :func:`rescu.core.run_image` with the default config in a
fresh Python process (as ``rescu discover`` does for one photo: the imports and the
backbone's loading count) and prints, per run, the seconds of the imports, of each stage
(every :func:`rescu.core.attempt`: prepare, features, dense, rescu-i (stage I), stage2-..., scene,
image-vp, caption, ...), the whole run, and the peak resident memory of that process
(``VmHWM``: it runs every stage itself, no child, so this is its whole process tree's
peak). The parent imports neither NumPy nor torch. Run it on an idle machine; it asserts
nothing. The issue's target: <= 3 s and <= 1 GB for a 1-MP photo.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CHILD = r'''
import json, re, sys, time
t0 = time.perf_counter()
import numpy as np
import rescu.core as core
from rescu.config import load_config
t_import = time.perf_counter() - t0
stages = {}
real = core.attempt

def timed(stage, step):
    t = time.perf_counter()
    try:
        return real(stage, step)
    finally:
        stages[stage] = stages.get(stage, 0.0) + time.perf_counter() - t

core.attempt = timed
import yaml
over = {}
for item in json.loads(sys.argv[3]):
    key, value = item.split("=", 1)
    node = over
    *parents, last = key.split(".")
    for k in parents:
        node = node.setdefault(k, {})
    node[last] = yaml.safe_load(value)
cfg = load_config(None, over or None, stage2=sys.argv[2] == "rescu-ii")
t = time.perf_counter()
out = core.run_image(sys.argv[1], cfg, sys.argv[2])
t_run = time.perf_counter() - t
hwm = int(re.search(r"VmHWM:\s+(\d+)", open("/proc/self/status").read())[1]) * 1024
print(json.dumps({"import_s": t_import, "run_s": t_run, "stages": stages,
                  "peak_bytes": hwm, "patterns": len(out.result.patterns),
                  "failure": out.result.extra.get("failure")}))
'''


def default_photos() -> list[Path]:
    """The first photo of two real sets when ``../shared/data`` is there, else two of
    the package photos."""
    data = REPO.parent / "shared" / "data"
    found = []
    for name in ("spb_facades", "blood_cells"):
        imgs = sorted((data / name / "images").glob("*.jpg"))
        if imgs:
            found.append(imgs[0])
    if found:
        return found
    sys.path.insert(0, str(REPO))
    from rescu.data.photos import package_photo_dir  # noqa: PLC0415

    return [package_photo_dir() / n for n in ("brick.png", "coins.png")]


def resized(photo: Path, mp: float, folder: Path) -> Path:
    """``photo`` resized to about ``mp`` megapixels (aspect kept), as PNG in ``folder``."""
    import cv2

    img = cv2.imread(str(photo), cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"{photo}: not readable")
    h, w = img.shape[:2]
    s = (mp * 1e6 / (w * h)) ** 0.5
    size = (max(16, round(w * s)), max(16, round(h * s)))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
    out = folder / f"{photo.stem}_{mp:g}MP.png"
    cv2.imwrite(str(out), img)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photo", action="append", type=Path, default=None)
    ap.add_argument("--mp", action="append", type=float, default=None)
    ap.add_argument("--method", default="rescu-ii", choices=["rescu-ii", "rescu-i"])
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override, as rescu discover --set (e.g. dense.enabled=false)")
    a = ap.parse_args(argv)
    photos = a.photo or default_photos()
    sizes = a.mp or [0.25, 1.0, 4.0, 12.0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for photo in photos:
            for mp in sizes:
                path = resized(photo, mp, Path(tmp))
                proc = subprocess.run([sys.executable, "-c", CHILD, str(path), a.method,
                                       json.dumps(a.sets)],
                                      capture_output=True, text=True, cwd=REPO)
                if proc.returncode != 0:
                    print(f"{path.name}: failed\n{proc.stderr[-2000:]}", file=sys.stderr)
                    continue
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                rows.append((photo.name, mp, r))
                st = "  ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
                print(f"{photo.name:28s} {mp:5g} MP  imports {r['import_s']:.2f} s  run "
                      f"{r['run_s']:6.2f} s  peak {r['peak_bytes'] / 2**20:6.0f} MiB  "
                      f"RPs {r['patterns']}  [{st}]", flush=True)
    if rows:
        print("\n| photo | MP | imports (s) | run (s) | peak (MiB) | slowest stages (s) |")
        print("|---|---|---|---|---|---|")
        for name, mp, r in rows:
            top = sorted(r["stages"].items(), key=lambda kv: -kv[1])[:4]
            print(f"| {name} | {mp:g} | {r['import_s']:.2f} | {r['run_s']:.2f} | "
                  f"{r['peak_bytes'] / 2**20:.0f} | "
                  + ", ".join(f"{k} {v:.2f}" for k, v in top) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
