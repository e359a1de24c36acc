"""Compare two results folders of the same datasets file by file.

    python benchmarks/compare_runs.py RESULTS_A RESULTS_B

For every file both runs made (logs, Snakemake benchmark timings and the code stamps
under ``.code/`` aside, which differ between any two runs), prints how many are
byte-identical, and for the others whether their *content* is equal once what always
differs between two runs is left out: a prepared image's ``source`` path (it names the
results folder), the stage-I search's wall-clock ``timings`` attribute of ``*.rp.h5``,
and the archive name inside a ``torch.save`` checkpoint. Files whose content differs are
listed; exit status 1 when there is any, or when a file is in one run only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

SKIP = (".code/", "logs/", "benchmarks/", ".snakemake/")


def _files(root: Path) -> dict[str, Path]:
    return {str(p.relative_to(root)): p for p in root.rglob("*")
            if p.is_file() and not str(p.relative_to(root)).startswith(SKIP)}


def _equal(x: Any, y: Any) -> bool:
    import torch

    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(_equal(x[k], y[k]) for k in x)
    if isinstance(x, (list, tuple)):
        return len(x) == len(y) and all(_equal(a, b) for a, b in zip(x, y))
    if torch.is_tensor(x):
        return torch.is_tensor(y) and torch.equal(x, y)
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        return np.array_equal(np.asarray(x), np.asarray(y))
    return bool(x == y)


def same_content(a: Path, b: Path) -> bool:
    """Whether two result files hold the same content, run-specific parts left out."""
    from rescu import io

    name = a.name
    if name.endswith(".json"):
        x, y = json.loads(a.read_text()), json.loads(b.read_text())
        if name.endswith(".meta.json"):
            x.pop("source", None), y.pop("source", None)
        return x == y
    if name.endswith(".h5"):
        (x, xa), (y, ya) = io.read_h5(a), io.read_h5(b)
        xa.pop("timings", None), ya.pop("timings", None)
        return _equal(x, y) and _equal(xa, ya)
    if name.endswith(".pt"):
        import torch

        return _equal(torch.load(a, weights_only=True), torch.load(b, weights_only=True))
    return False


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    fa, fb = _files(args.a), _files(args.b)
    sha = lambda p: hashlib.sha256(p.read_bytes()).digest()  # noqa: E731
    common = sorted(set(fa) & set(fb))
    identical = [k for k in common if sha(fa[k]) == sha(fb[k])]
    other = [k for k in common if k not in set(identical)]
    content = [k for k in other if same_content(fa[k], fb[k])]
    differ = [k for k in other if k not in set(content)]
    only = sorted(set(fa) ^ set(fb))
    print(f"{len(common)} files in both runs: {len(identical)} byte-identical, "
          f"{len(content)} with equal content (run-specific parts aside), "
          f"{len(differ)} different; {len(only)} in one run only")
    kinds = Counter("/".join(k.split("/")[:2]) + "/*" + "".join(Path(k).suffixes[-2:])
                    for k in content)
    for kind, n in sorted(kinds.items()):
        print(f"  equal content, not bytes: {n:4d} {kind}")
    for k in differ:
        print(f"  different: {k}")
    for k in only:
        print(f"  in one run only: {k}")
    return 1 if differ or only else 0


if __name__ == "__main__":
    sys.exit(main())
