"""The dominant RP chosen by other rules, scored on a quick_eval run without running it again.

    python ../shared/tools/quick_eval.py run before              # once, on the code as it is
    python benchmarks/studies/dominant_rules.py results/quick/before

For every photo of a ``quick_eval.py`` run (``results/quick/<label>/<set>/*.json``, the
default ``rescu discover`` results), the dominant RP is chosen again among the reported
RPs by each rule of :data:`benchmarks.studies.rp_sources.DOMINANT` (``code``: the
code's, the most confident; ``objects``: the RP of whole objects with the most
instances; ``count``; ``count-near-best``; ...), written into a copy of the results
(only ``dominant_pattern`` changes) and scored by quick_eval's own scoring: the
many-object sets (the dominant RP against the ``count_class`` boxes: cover, precision,
mean and median relative count error) and, for the RP sets, the dominant RP against the
image's largest GT RP (covered share, precision, median relative count error; IOD >
0.5, one to one). The synthetic benchmark's figure for the same rules comes from
``rp_sources.py <results> --dominant <rule>``. Needs ``../shared`` (quick_eval and the
data); asserts nothing. What the rules do not see: the image VP starts from the dominant
RP, so a rule that changes it moves york_urban's VP too (not scored here).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(Path(__file__).resolve().parent)]

from rp_sources import DOMINANT, pick_dominant  # noqa: E402


def _quick_eval():
    """quick_eval's module, from ``../shared/tools``."""
    tools = REPO.parent / "shared" / "tools"
    if not (tools / "quick_eval.py").is_file():
        raise SystemExit(f"{tools}/quick_eval.py not found: this study needs ../shared")
    sys.path.insert(0, str(tools))
    import quick_eval  # noqa: PLC0415

    return quick_eval


def rechoose(src: Path, dst: Path, rule: str) -> None:
    """Copy the result JSONs of ``src`` into ``dst`` with ``dominant_pattern`` by ``rule``."""
    from rescu.types import ImageResult

    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.glob("*.json")):
        d = json.loads(f.read_text())
        if "patterns" in d:
            res = ImageResult.from_json(d)
            k = pick_dominant(res.patterns, rule)
            d["dominant_pattern"] = None if k is None else int(res.patterns[k].id)
        (dst / f.name).write_text(json.dumps(d))


def largest_rp(Q, root: Path, s: str, out: Path) -> dict[str, float]:
    """The dominant RP of each photo of RP set ``s`` against its largest GT RP (two or
    more boxes of one category): mean covered share, mean precision, median relative
    count error."""
    import numpy as np

    coco = json.loads((root / s / "annotations.json").read_text())
    by: dict[int, dict[int, list]] = {}
    for an in coco["annotations"]:
        by.setdefault(an["image_id"], {}).setdefault(an["category_id"], []).append(an["bbox"])
    rows = []
    for im in coco["images"]:
        r = Q.result(out, im["file_name"])
        cats = [b for b in by.get(im["id"], {}).values() if len(b) >= 2]
        if r is None or not cats:
            continue
        gt = max(cats, key=len)
        dom = {p.get("id"): p for p in r.get("patterns", [])}.get(r.get("dominant_pattern"))
        boxes = [i["bbox"] for i in dom["instances"]] if dom else []
        m = Q.matching(Q.iod(boxes, gt) > 0.5) if boxes else 0
        rows.append((m / len(gt), m / len(boxes) if boxes else 0.0,
                     abs(len(boxes) - len(gt)) / len(gt)))
    if not rows:
        return {"photos": 0}
    a = np.asarray(rows)
    return {"photos": len(rows), "cover": float(a[:, 0].mean()), "P": float(a[:, 1].mean()),
            "err_median": float(np.median(a[:, 2]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a quick_eval run folder, results/quick/<label>")
    ap.add_argument("--rule", action="append", choices=list(DOMINANT), default=None)
    a = ap.parse_args(argv)
    Q = _quick_eval()
    root = Q.shared_data()
    rules = a.rule or ["code", "objects", "count", "count-near-best"]
    sets = [s for s in Q.COUNT_SETS + Q.RP_SETS if (a.run / s).is_dir()]
    print("| set | " + " | ".join(rules) + " |")
    print("|---|" + "---|" * len(rules))
    with tempfile.TemporaryDirectory() as tmp:
        for s in sets:
            cells, n = [], 0
            for rule in rules:
                out = Path(tmp) / rule / s
                rechoose(a.run / s, out, rule)
                if s in Q.COUNT_SETS:
                    x = Q.score_count(root, s, out)
                    n = x.get("photos", 0)
                    cells.append(f"{x['cover']:.2f} / {x['P']:.2f} / {x['err_mean']:.2f} / "
                                 f"{x['err_median']:.2f}" if x.get("photos") else "-")
                else:
                    x = largest_rp(Q, root, s, out)
                    n = x.get("photos", 0)
                    cells.append(f"{x['cover']:.2f} / {x['P']:.2f} / {x['err_median']:.2f}"
                                 if x.get("photos") else "-")
            print(f"| {s} ({n}) | " + " | ".join(cells) + " |")
    print("\nmany-object sets: cover / precision / mean / median relative count error against "
          "count_class; RP sets: the largest GT RP's covered share / precision / median "
          "relative count error")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
