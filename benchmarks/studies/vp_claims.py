"""Which image VPs a result may claim: the claim test of stored results, before and after.

Reads ``rescu discover`` results (``RUN/<set>/<stem>.json``, one folder per dataset of
``../shared/data``), whose claims the code that made them decided ("before"), and
decides them again with the current code and configuration
(:func:`rescu.scene.claims.supported_claims` on the same evidence: every VP of the joint
estimator, kept or rejected, with its inliers and the lines it was drawn from; "after").
Then, with the project's own VP scorer (:func:`rescu.evaluation.vpd.vp_frame`):

- sets with ``vanishing_points.json`` (York Urban): the image VP against the closest true
  VP, with the true focal length: share within 5 degrees (no VP = a miss), median angle;
- ``cmp_facade`` (rectified facades): the same against the derived truth (rows and
  columns meet at the points at infinity; :func:`rescu.data.datasets.rectified_vp_truth`);
- every other set (blood smears, nuclei: flat scans, no VP): the share of photos that
  claim a VP, and of those at infinity;
- every set: the NFA of each photo's best VP with the test off (``max_image_nfa``
  1e300): its least, median and largest log10 over the photos (inf: no VP listed).

Usage (from the repository root)::

    for s in york_urban cmp_facade blood_cells nuclei; do
        rescu discover ../shared/data/$s/images --out RUN/$s; done
    python benchmarks/studies/vp_claims.py RUN
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2])]

RECTIFIED = ("cmp_facade",)


def regated(res_json: dict, claims: dict) -> dict:
    """The result's claims decided again on its stored evidence (see the module
    docstring)."""
    from rescu.scene.claims import ClaimParams, supported_claims
    from rescu.types import ImageResult

    d = json.loads(json.dumps(res_json))
    listed = [{k: v for k, v in e.items() if k not in ("status", "nfa")}
              for e in (d.get("vanishing_points") or []) + (
                  d.get("rejected_vanishing_points") or [])]
    if listed:
        d["vanishing_points"] = sorted(listed, key=lambda e: -float(e.get("support", 0)))
        d["rejected_vanishing_points"] = []
    res = supported_claims(ImageResult.from_json(d), ClaimParams.from_dict(claims))
    return res.to_json()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="RUN: one folder of results per dataset")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    a = ap.parse_args(argv)

    from rescu.config import load_config
    from rescu.data.datasets import rectified_vp_truth
    from rescu.evaluation.vpd import vp_frame

    claims = load_config(None)["scene"]["claims"]
    tmp = Path(tempfile.mkdtemp(prefix="vp_claims."))
    for folder in sorted(p for p in a.run.iterdir() if p.is_dir()):
        name = folder.name
        files = sorted(folder.glob("*.json"))
        after = tmp / name / "after"
        after.mkdir(parents=True)
        status: dict[str, list[str]] = {"before": [], "after": []}
        best = []
        for f in files:
            d = json.loads(f.read_text())
            if "width" not in d:
                continue
            g = regated(d, claims)
            nfas = [float(v["nfa"]) for v in regated(d, {**claims, "max_image_nfa": 1e300}
                                                     ).get("vanishing_points") or []]
            best.append(min(nfas) if nfas else np.inf)
            (after / f.name).write_text(json.dumps(g))
            for key, r in (("before", d), ("after", g)):
                vp = r.get("vanishing_point")
                status[key].append("none" if not vp else
                                   "infinity" if abs(float(vp["homogeneous"][2])) < 1e-9
                                   else "finite")
        root = a.data / name
        truth = None
        if name in RECTIFIED and (root / "annotations.json").is_file():
            truth = tmp / name / "truth.json"
            truth.write_text(json.dumps(rectified_vp_truth(
                json.loads((root / "annotations.json").read_text()))))
        elif (root / "vanishing_points.json").is_file():
            truth = root / "vanishing_points.json"
        n = len(status["before"])
        line = f"{name:12s} {n:3d} photos"
        if truth is not None:
            fr = vp_frame(root, {"before": folder, "after": after}, truth=truth)
            fr = fr[fr["image"].map(lambda s: (folder / (Path(s).stem + ".json")).is_file())]
            for m in ("before", "after"):
                e = fr[fr["method"] == m]["angle_error_deg"].astype(float).fillna(np.inf)
                line += (f" | {m}: sr@5 {float((e <= 5).mean()):.2f} median "
                         f"{float(np.median(e)):.2f} deg, no VP {int(np.isinf(e).sum())}")
        for m in ("before", "after"):
            st = status[m]
            line += (f" | {m}: VP claimed {sum(s != 'none' for s in st) / max(n, 1):.2f} "
                     f"(at infinity {sum(s == 'infinity' for s in st) / max(n, 1):.2f})")
        lg = np.log10(np.maximum(np.array(best, float), 1e-300)) if best else np.array([])
        if len(lg):
            line += (f" | best VP's log10 NFA: least {lg.min():.0f} median "
                     f"{np.median(lg):.0f} largest {lg.max():.0f}")
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
