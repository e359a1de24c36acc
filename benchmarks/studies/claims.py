"""False claims of a finished run: which final JSONs state a vanishing point, a grid or
translation symmetry, against what the images have.

For every ``<results>/<dataset>/final/*.json`` (or a ``rescu discover`` folder of
JSONs): the image VP (``vanishing_point``, its ``vp_status``), the dominant RP's VP,
whether the caption and the summary line say "vanishing point" / "VP", "grid" and
"translation symmetry", and whether they agree. With ``--truth`` (a dataset's
``vanishing_points.json``) the images without a true VP (the synthetic frontal ones)
count as *false* image-VP and RP-VP claims when a VP is stated.

    .venv/bin/python benchmarks/studies/claims.py results/synthetic/final \\
        --truth results/data/synthetic/vanishing_points.json
    .venv/bin/python benchmarks/studies/claims.py results/photos/final
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rescu.captions.caption import dominant_pattern, scene_facts, summary_line
from rescu.io import read_result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", help="a folder of per-image final JSONs")
    p.add_argument("--truth", default=None, help="vanishing_points.json of the dataset")
    a = p.parse_args(argv)
    truth = None
    if a.truth:
        truth = {Path(i["file_name"]).stem: bool(i.get("vanishing_points"))
                 for i in json.loads(Path(a.truth).read_text())["images"]}
    rows, disagree = [], 0
    for f in sorted(Path(a.folder).glob("*.json")):
        r = read_result(f)
        if r.extra.get("failure") and not r.extra["failure"].get("degraded_to"):
            continue
        cap = (r.caption or {}).get("enhanced") or ""
        line = summary_line(r)
        facts = scene_facts(r)
        dom = dominant_pattern(r)
        said_vp = "vanishing point" in cap
        agree = (said_vp == ("VP " in line) == (facts.vp is not None)
                 and ("grid" in cap) == ("grid" in line)
                 and ("symmetry" in cap) == ("symmetry" in line))
        disagree += not agree
        rows.append({"image": f.stem, "has_vp": None if truth is None else truth.get(f.stem),
                     "image_vp": r.vanishing_point is not None,
                     "vp_status": r.extra.get("vp_status"),
                     "rp_vp": dom is not None and dom.vanishing_point is not None,
                     "rp_vp_status": None if dom is None else dom.extra.get("vp_status"),
                     "caption_vp": said_vp, "grid": facts.layout == "grid", "ts": facts.ts,
                     "agree": agree})
    print("image\ttrue VP\timage VP (status)\tdominant RP VP (status)\tcaption VP\tgrid\tTS\t"
          "caption = summary")
    for r in rows:
        print(f"{r['image']}\t{r['has_vp']}\t{r['image_vp']} ({r['vp_status']})\t"
              f"{r['rp_vp']} ({r['rp_vp_status']})\t{r['caption_vp']}\t{r['grid']}\t"
              f"{r['ts']}\t{r['agree']}")
    n = len(rows)
    print(f"\n{n} images: image VP stated in {sum(r['image_vp'] for r in rows)}, the "
          f"dominant RP's VP in {sum(r['rp_vp'] for r in rows)}, a VP sentence in "
          f"{sum(r['caption_vp'] for r in rows)}; caption and summary line disagree on "
          f"{disagree}")
    if truth is not None:
        none = [r for r in rows if r["has_vp"] is False]
        print(f"without a true VP ({len(none)}): image VP stated in "
              f"{sum(r['image_vp'] for r in none)}, an RP VP in "
              f"{sum(r['rp_vp'] for r in none)}, a VP sentence in "
              f"{sum(r['caption_vp'] for r in none)}")
        some = [r for r in rows if r["has_vp"]]
        print(f"with a true VP ({len(some)}): image VP stated in "
              f"{sum(r['image_vp'] for r in some)}, an RP VP in "
              f"{sum(r['rp_vp'] for r in some)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
