"""A self-contained HTML report: tables, curves, and pictures of what was found."""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any, Sequence

from .io import atomic_path


def _img_tag(path: str | Path, width: int | None = None) -> str:
    """An <img> with the picture embedded as a JPEG at most twice ``width`` pixels wide
    (sharp on high-density screens, small enough to keep the report portable)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        return f"<p><em>(unreadable picture {html.escape(Path(path).name)})</em></p>"
    if width and img.shape[1] > 2 * width:
        f = 2 * width / img.shape[1]
        img = cv2.resize(img, (2 * width, max(1, round(img.shape[0] * f))),
                         interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    data = base64.b64encode(buf.tobytes()).decode("ascii")
    w = f' width="{width}"' if width else ""
    return f'<img src="data:image/jpeg;base64,{data}"{w} alt="{html.escape(Path(path).name)}">'


def _table_html(tsv: str | Path) -> str:
    import pandas as pd

    p = Path(tsv)
    if not p.exists() or p.stat().st_size == 0:
        return "<p><em>(no rows)</em></p>"
    df = pd.read_csv(p, sep="\t")
    if df.empty:
        return "<p><em>(no rows)</em></p>"
    return df.to_html(index=False, na_rep="–", float_format=lambda v: f"{v:.3f}", border=0,
                      classes="t")


def build_report(out_html: str | Path, title: str, intro: str,
                 tables: Sequence[tuple[str, str | Path]], figures: Sequence[str | Path],
                 samples: Sequence[dict[str, Any]]) -> None:
    """Write one HTML file with everything embedded (no external files).

    Parameters
    ----------
    tables : list of ``(heading, tsv_path)``
    figures : list of PNG paths (curves)
    samples : list of ``{"dataset", "image", "overlay": png, "rectified": [png, ...],
        "caption": str, "summary": str}``
    """
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
             "</title><style>body{font-family:sans-serif;max-width:1200px;margin:auto;"
             "padding:1em}table.t{border-collapse:collapse;font-size:13px;margin:0.5em 0 1.5em}"
             "table.t td,table.t th{border-bottom:1px solid #ddd;padding:3px 8px;"
             "text-align:right}figure{display:inline-block;margin:6px;vertical-align:top;"
             "max-width:560px}figcaption{font-size:13px}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", f"<p>{intro}</p>", "<h2>Tables</h2>"]
    for heading, tsv in tables:
        parts.append(f"<h3>{html.escape(heading)}</h3>")
        parts.append(_table_html(tsv))
    if figures:
        parts.append("<h2>Curves</h2>")
        for f in figures:
            if Path(f).exists():
                parts.append(f"<figure>{_img_tag(f, 540)}<figcaption>{html.escape(Path(f).stem)}"
                             "</figcaption></figure>")
    parts.append("<h2>What was found (sample images)</h2>")
    current = None
    for s in samples:
        if s["dataset"] != current:
            current = s["dataset"]
            parts.append(f"<h3>{html.escape(current)}</h3>")
        rect = "".join(_img_tag(r, 160) for r in s.get("rectified", []))
        parts.append(
            f"<figure>{_img_tag(s['overlay'], 540)}<figcaption><b>{html.escape(s['image'])}</b>: "
            f"{html.escape(s.get('summary', ''))}<br><i>{html.escape(s.get('caption', ''))}</i>"
            f"{'<br>rectified: ' + rect if rect else ''}</figcaption></figure>")
    parts.append("</body></html>")
    with atomic_path(out_html) as tmp:
        tmp.write_text("\n".join(parts))


def build_run_report(out_html: str | Path, results: str | Path,
                     samples: dict[str, list[str]]) -> None:
    """The report of a pipeline run from its results folder.

    ``samples`` maps each dataset to the image stems whose overlays are shown.
    """
    from .io import read_result

    results = Path(results)
    t = results / "tables"
    tables = [("RP discovery (mean, std, n per metric)", t / "rp_discovery.tsv"),
              ("Stage-I ablation: adaptive parameters and orientation mode", t / "ablation.tsv"),
              ("Stage-II ablation: proposals", t / "stage2_ablation.tsv"),
              ("Counting", t / "counting.tsv"),
              ("Vanishing-point detection: success rates", t / "vpd.tsv"),
              ("Vanishing points: paired tests", t / "vpd_tests.tsv"),
              ("Translation symmetry: SR_ts vs t", t / "ts.tsv"),
              ("Failures (image, stage, message)", t / "failures.tsv"),
              ("Captions", t / "captions.tsv")]
    tables = [(h, p) for h, p in tables if p.exists()]  # ablations only in `paper` runs
    figures = sorted((results / "figures").glob("*.png"))
    items = []
    for ds, stems in samples.items():
        for stem in stems:
            res = read_result(results / ds / "final" / f"{stem}.json")
            rect_dir = results / ds / "rectified" / stem
            rect = sorted(rect_dir.glob("*.png")) if rect_dir.is_dir() else []
            f = res.extra.get("failure")
            summary = (f"failed in {f.get('stage')}: {f.get('message')}" if f else
                       f"{len(res.patterns)} pattern(s), counts "
                       f"{', '.join(str(p.count) for p in res.patterns) or '-'}")
            items.append({"dataset": ds, "image": res.image or stem,
                          "overlay": results / ds / "overlay" / f"{stem}.png",
                          "rectified": rect, "summary": summary,
                          "caption": (res.caption or {}).get("enhanced", "")})
    summary_md = t / "summary.md"
    intro = ("Recurring patterns found without training data or labels; vanishing points from "
             "the implicit lines of the patterns; translation symmetry by the cross ratio; "
             "counts; captions. Tables: mean ± std over images. " +
             (html.escape(summary_md.read_text().splitlines()[2]) if summary_md.exists()
              and len(summary_md.read_text().splitlines()) > 2 else ""))
    build_report(out_html, "RESCU report", intro, tables, figures, items)
