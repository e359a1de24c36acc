"""A self-contained HTML report that reads top-down: per dataset the headline figures
beside pictures of what was found, then each evaluation as a compact table next to its
curve (long per-threshold tables as a plot and a link to their TSV), then the ablations
and diagnostics.

Everything is embedded (pictures as base64 JPEG), except the links to the TSV tables,
which are relative to the HTML file (``../tables/<name>.tsv`` in a run's results folder).
:func:`chromium_layout` and :func:`chromium_screenshot` look at the page the way a
reader does, in headless Chromium. The tables themselves (column names, cells, headline
and compact tables) are built by :mod:`rescu.evaluation.report_tables`.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import pandas as pd

from ..io import atomic_path
from ..pages import img_tag
from .report_tables import (_num, counting_compact, found_headline, human_name, md_inline,
                            plain_table, read_tsv, rp_headline, summary_cells, ts_compact,
                            vp_compact, vp_headline)


# ----------------------------------------------------------------------------- pictures
def _plural(n: Any, word: str) -> str:
    """``"1 image"``, ``"3 images"``."""
    return f"{_num(n)} {word}{'' if _num(n) == '1' else 's'}"


def _anchor(*parts: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "-", "-".join(parts)).strip("-")


@dataclass
class Sample:
    """One picture of what was found: dataset, image name, overlay PNG, rectified views,
    a one-line summary (patterns and counts, or the failure) and the caption."""

    dataset: str
    image: str
    overlay: Path
    rectified: list[Path] = field(default_factory=list)
    summary: str = ""
    caption: str = ""
    found: bool = False
    failed: bool = False
    confidence: float | None = None

    @property
    def anchor(self) -> str:
        return _anchor("img", self.dataset, Path(self.image).stem)


BENCHMARKS = ("synthetic",)
"""Datasets that are generated benchmarks, not photos: shown after the photos."""


def pick_photos(samples: Sequence[Sample], n: int,
                benchmarks: Sequence[str] = BENCHMARKS) -> list[Sample]:
    """The pictures of the report's first screen: up to ``n`` real photos (datasets not
    in ``benchmarks``; all datasets when there is none), the most confident results
    first (a pattern's ``confidence`` where discovery gave one, else its score) taken in
    turn from each dataset, then up to ``max(1, n // 4)`` without a pattern or failed."""
    real = [s for s in samples if s.dataset not in benchmarks] or list(samples)
    good = [s for s in real if s.found and not s.failed]
    bad = [s for s in real if not s.found or s.failed]
    k_bad = min(len(bad), max(1, n // 4)) if n else 0
    by_ds: dict[str, list[Sample]] = {}
    for s in sorted(good, key=lambda s: -(s.confidence if s.confidence is not None
                                          else float("-inf"))):
        by_ds.setdefault(s.dataset, []).append(s)
    picked: list[Sample] = []
    while len(picked) < n - k_bad and any(by_ds.values()):
        for ds in list(by_ds):
            if by_ds[ds] and len(picked) < n - k_bad:
                picked.append(by_ds[ds].pop(0))
    return picked + bad[:n - len(picked)]


def skipped_note(skipped: Mapping[str, str]) -> str:
    """One HTML paragraph naming the datasets left out of the run and why, and how to add
    a dataset.

    >>> print(skipped_note({"chess": "folder ../shared/data/chess not found"}))
    <p class='note skipped'>Not in this run: <b>chess</b> (folder ../shared/data/chess not found). A dataset is a folder of photos (<code>images/</code> with <code>annotations.json</code> for the tables, or just photos) named under <code>datasets</code> in <code>config/config.yaml</code> or a file passed with <code>--configfile</code>; see the README, &quot;Your own photos&quot;.</p>
    """
    names = "; ".join(f"<b>{html.escape(n)}</b> ({html.escape(why)})"
                      for n, why in skipped.items())
    return ("<p class='note skipped'>Not in this run: " + names + ". A dataset is a folder "
            "of photos (<code>images/</code> with <code>annotations.json</code> for the "
            "tables, or just photos) named under <code>datasets</code> in "
            "<code>config/config.yaml</code> or a file passed with "
            "<code>--configfile</code>; see the README, &quot;Your own photos&quot;.</p>")


def _full_link(s: Sample, out_html: Path, inner: str) -> str:
    """``inner`` (a picture) as a link to the full-size overlay, relative to the page."""
    href = os.path.relpath(Path(s.overlay).resolve(), Path(out_html).resolve().parent)
    return f"<a href='{html.escape(Path(href).as_posix())}' title='full size'>{inner}</a>"


# ----------------------------------------------------------------------------- page
CSS = """
*{box-sizing:border-box}
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;
 color:#1d1d1f;margin:0 auto;padding:12px 20px 40px;max-width:1360px;line-height:1.35}
h1{font-size:26px;margin:4px 0 2px}
h2{font-size:20px;margin:28px 0 6px;padding-top:8px;border-top:2px solid #ddd}
h3{font-size:16px;margin:8px 0 4px}
h3 .sub{font-weight:normal;color:#666;font-size:13px;margin-left:6px}
p{margin:4px 0}
.lead{font-size:15px;margin:0 0 2px}
.meta,.note{font-size:12.5px;color:#555}
nav{font-size:13px;margin:4px 0 6px}
nav a{margin-right:12px}
a{color:#0b5cad}
.tw{max-width:100%;overflow-x:auto}
table.t{border-collapse:collapse;font-size:13px;margin:2px 0 6px}
table.t th{font-weight:600;vertical-align:bottom;padding:3px 7px;border-bottom:2px solid #999;
 max-width:9em;white-space:normal;text-align:right}
table.t td{padding:2px 7px;border-bottom:1px solid #e4e4e4;white-space:nowrap;
 text-align:right;font-variant-numeric:tabular-nums}
table.t th.txt,table.t td.txt,table.t th.wrap,table.t td.wrap{text-align:left}
table.t td.wrap{white-space:normal;min-width:14em;max-width:38em}
table.t th.wrap{max-width:none}
table.headline{font-size:14px}
table.headline th{max-width:7em}
.ds{display:flex;flex-wrap:wrap;gap:8px 22px;align-items:flex-start;padding:6px 0 8px;
 border-bottom:1px solid #eee}
.ds .nums{flex:0 0 610px;max-width:100%}
.thumbs{display:flex;gap:8px;flex-wrap:wrap}
.thumbs figure{margin:0}
.thumbs figcaption{font-size:11.5px;color:#444;max-width:240px;white-space:nowrap;
 overflow:hidden;text-overflow:ellipsis}
.pair{display:flex;flex-wrap:wrap;gap:8px 24px;align-items:flex-start}
.pair>div{flex:0 1 auto;max-width:100%}
.pair>div.fig{flex:1 1 420px;min-width:0}
figure{margin:4px 0}
figure img,.pair img{max-width:100%;height:auto}
.gallery{display:flex;flex-wrap:wrap;gap:14px}
.gallery figure{width:316px;margin:0}
.gallery figcaption{font-size:14px}
.gallery .cap,.picks .cap{font-style:italic;margin-top:2px}
.picks{display:flex;flex-wrap:wrap;gap:14px 18px;margin:6px 0 10px}
.picks figure{width:420px;max-width:100%;margin:0}
.picks figcaption{font-size:14.5px}
.picks .name{font-weight:600}
.failed{color:#a00}
.gallery .rect img{margin:2px 4px 0 0}
details summary{cursor:pointer;font-size:13px;color:#0b5cad}
code{font-size:12px}
"""

#: Runs only when the page is opened with ``#check``: writes the page's layout (window
#: and page width, each table's box, the first headline table's and first picture's
#: boxes) as JSON into ``<pre id="layout-check">``, for :func:`chromium_layout`.
CHECK_JS = """
(function(){
 if(location.hash!=="#check")return;
 function box(e){if(!e)return null;var r=e.getBoundingClientRect();
  return {left:r.left,top:r.top+scrollY,right:r.right,bottom:r.bottom+scrollY,
          width:r.width,height:r.height};}
 var de=document.documentElement,out={innerWidth:innerWidth,innerHeight:innerHeight,
  clientWidth:de.clientWidth,scrollWidth:de.scrollWidth,bodyScrollWidth:document.body.scrollWidth,
  tables:[],headline:box(document.querySelector("table.headline")),
  firstImg:box(document.querySelector("img")),imgsOnFirstScreen:0,
  firstH2:box(document.querySelector("h2")),
  firstCaption:box(document.querySelector(".picks figcaption")),
  captionFontPx:(function(e){return e?parseFloat(getComputedStyle(e).fontSize):0;})(
   document.querySelector(".picks figcaption"))};
 document.querySelectorAll("table").forEach(function(t){var b=box(t);
  b.cls=t.className;b.scrollWidth=t.scrollWidth;out.tables.push(b);});
 document.querySelectorAll("img").forEach(function(i){var b=box(i);
  if(b.top<innerHeight&&b.bottom>0&&b.width>0)out.imgsOnFirstScreen++;});
 var pre=document.getElementById("layout-check")||document.createElement("pre");
 pre.id="layout-check";pre.style.display="none";pre.textContent=JSON.stringify(out);
 document.body.appendChild(pre);
})();
"""


def _tsv_link(path: Path, out_html: Path, label: str | None = None) -> str:
    rel = os.path.relpath(path, out_html.parent).replace(os.sep, "/")
    return f'<a href="{html.escape(rel)}">{html.escape(label or path.name)}</a>'


def _figure(path: Path, width: int, caption: str = "") -> str:
    cap = f"<figcaption class='note'>{caption}</figcaption>" if caption else ""
    return f"<figure>{img_tag(path, width=width)}{cap}</figure>"


def _datasets(samples: Sequence[Sample], *frames: pd.DataFrame | None,
              order: Sequence[str] = ()) -> list[str]:
    """The datasets that the samples and frames name, those of ``order`` first in its
    order (the run's), the others as they come."""
    names = [s.dataset for s in samples]
    for f in frames:
        if f is not None and "dataset" in f.columns:
            names += [str(d) for d in f["dataset"]]
    names = list(dict.fromkeys(names))
    return [d for d in order if d in names] + [d for d in names if d not in order]


def build_report(out_html: str | Path, tables_dir: str | Path, figures_dir: str | Path,
                 samples: Sequence[Sample], datasets: Sequence[str] | None = None,
                 title: str = "RESCU report", meta: str = "", alpha: float = 0.05,
                 iod_h: float | None = None, decimals: int = 2, thumbs: int = 3,
                 tables: Iterable[str | Path] | None = None, first_screen: int = 8,
                 skipped: Mapping[str, str] | None = None) -> None:
    """Write the report: one HTML file with everything embedded but the TSV links.

    Parameters
    ----------
    tables_dir, figures_dir : folders of the run's tables (``*.tsv``; the ones that do
        not exist are left out) and curves (``rp_curves_<dataset>.png``,
        ``vpd_<dataset>.png``, ``ts_sweep.png``)
    samples : pictures of what was found, in dataset order; :func:`pick_photos` picks
        ``first_screen`` of them (real photos) for the top of the page, the first
        ``thumbs`` of a dataset stand beside its headline, all are in the pictures
        section, each a link to the full-size picture
    datasets : the datasets of the run in order (default: as the samples and tables
        name them)
    meta : one line of Markdown under the title (what produced the tables)
    alpha, iod_h : the significance level of the paired tests (italics) and the IOD
        threshold of the tables, as the run used them (for the notes)
    tables : the table files this run made (default: every one in ``tables_dir``); one
        left out here is not shown even if an earlier run left it there (e.g. the
        ablations of a ``paper`` run)
    skipped : configured datasets not in this run, each with the reason (its folder is
        missing): named under the first photos, with how to add a dataset
    """
    out_html, t, fig = Path(out_html), Path(tables_dir), Path(figures_dir)
    made = None if tables is None else {Path(p).name for p in tables}

    def load(path: Path) -> pd.DataFrame | None:
        return None if made is not None and path.name not in made else read_tsv(path)

    rp = load(t / "rp_discovery.tsv")
    counting = load(t / "counting.tsv")
    vpd = load(t / "vpd.tsv")
    vp_err = load(t / "vpd_errors.tsv")
    vp_tests = load(t / "vpd_tests.tsv")
    ts = load(t / "ts.tsv")
    abl = load(t / "ablation.tsv")
    abl2 = load(t / "stage2_ablation.tsv")
    failures = load(t / "failures.tsv")
    captions = load(t / "captions.tsv")
    names = list(datasets) if datasets else _datasets(samples, captions, rp, vpd)
    names = ([n for n in names if n not in BENCHMARKS]       # photos first, the
             + [n for n in names if n in BENCHMARKS])         # benchmark after them
    picks = pick_photos(samples, first_screen)
    by_ds: dict[str, list[Sample]] = {}
    for s in samples:
        by_ds.setdefault(s.dataset, []).append(s)
    n_img = (captions.groupby("dataset").size().to_dict()
             if captions is not None and len(captions) else {})
    h = f"IOD h = {iod_h:g}" if iod_h is not None else "the IOD protocol"
    link = lambda name, label=None: _tsv_link(t / name, out_html, label)  # noqa: E731

    nav = [("photos", "Photos", picks or None), ("rp", "Recurring patterns", rp), ("counting", "Counting", counting),
           ("vp", "Vanishing points", vpd), ("ts", "Translation symmetry", ts),
           ("pictures", "Pictures", samples or None),
           ("ablations", "Ablations", abl if abl is not None else abl2),
           ("diagnostics", "Failures and captions", failures if failures is not None
            else captions)]
    n_total = sum(n_img.values()) if n_img else None
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<p class='lead'>Recurring patterns found in "
        + (f"{_plural(n_total, 'image')} of " if n_total else "")
        + f"{_plural(len(names), 'dataset')} without training data or "
        "labels: first photos with what was found (the most confident results and some "
        "without a pattern; a click opens the full picture), then per dataset the "
        "headline figures, the synthetic benchmark last, and each evaluation in "
        "detail.</p>",
        "<p class='meta'>" + (meta + " " if meta else "")
        + f"P / R: precision / recall of instances and of whole recurring patterns (RPs) at "
        f"{html.escape(h)}, mean ± std over images; <b>bold</b>: best. All tables as TSV in "
        + _tsv_link(t, out_html, "tables/") + ".</p>",
        "<nav>" + "".join(f"<a href='#{a}'>{label}</a>" for a, label, x in nav
                          if x is not None) + "</nav>"]

    # First: real photos with what was found.
    if picks:
        cards = []
        for p in picks:
            cap = (f"<div class='cap'>{html.escape(p.caption)}</div>"
                   if p.caption and p.caption != p.summary else "")
            cls = " class='failed'" if p.failed or not p.found else ""
            cards.append(
                f"<figure>{_full_link(p, out_html, img_tag(p.overlay, width=420, alt=p.image))}"
                f"<figcaption><span class='name'>{html.escape(Path(p.image).name)}</span> "
                f"<span class='sub'>({html.escape(p.dataset)})</span><div{cls}>"
                f"{html.escape(p.summary)}</div>{cap}</figcaption></figure>")
        parts.append("<section id='photos'><div class='picks'>" + "".join(cards)
                     + "</div></section>")
    if skipped:
        parts.append(skipped_note(skipped))

    # Per dataset: the headline beside the first pictures.
    for ds in names:
        tab, what = None, ""
        if rp is not None and len(rp):
            tab, what = rp_headline(rp, ds, decimals), "recurring-pattern ground truth"
        if tab is None and vpd is not None and len(vpd):
            tab, what = (vp_headline(vpd, ds, vp_err, decimals=decimals),
                         "vanishing-point ground truth")
        if tab is None and captions is not None and len(captions):
            tab, what = found_headline(captions, ds), "no ground truth: what RESCU-II found"
        if tab is None:
            what = ""
        sub = [_plural(n_img[ds], "image") if ds in n_img else "", what]
        parts.append(f"<section class='ds' id='{_anchor('ds', ds)}'><div class='nums'>"
                     f"<h3>{html.escape(ds)}<span class='sub'>"
                     f"{html.escape(' · '.join(x for x in sub if x))}</span></h3>"
                     + (tab.to_html() if tab is not None else
                        "<p class='note'>(no table for this dataset)</p>") + "</div>")
        th = []
        for s in by_ds.get(ds, [])[:thumbs]:
            th.append(f"<figure><a href='#{s.anchor}'>"
                      f"{img_tag(s.overlay, height=165, alt=Path(s.image).name)}</a>"
                      f"<figcaption title='{html.escape(s.caption)}'>"
                      f"{html.escape(Path(s.image).stem)}: {html.escape(s.summary)}"
                      "</figcaption></figure>")
        parts.append(f"<div class='thumbs'>{''.join(th)}</div></section>")

    # Recurring patterns: per dataset the full table (subsets) above its curves.
    if rp is not None:
        parts.append("<h2 id='rp'>Recurring patterns</h2><p class='note'>Mean ± std over "
                     f"images at {html.escape(h)}, per subset of the images; <b>bold</b>: best "
                     f"of the subset, <i>italics</i>: not significantly different from it "
                     f"(paired Wilcoxon, p ≥ {alpha:g}). Curves: the metrics as the IOD "
                     f"threshold h varies. {link('rp_discovery.tsv')}, per image: "
                     f"{link('rp_scores.tsv')}, curves: {link('rp_curves.tsv')}.</p>")
        for ds in _datasets([], rp, order=names):
            g = rp[rp["dataset"].astype(str) == ds]
            tab = summary_cells(g, ["subset", "method"], decimals=decimals, alpha=alpha)
            parts.append(f"<h3>{html.escape(ds)}</h3><div class='pair'><div>{tab.to_html()}"
                         "</div></div>")
            if (fig / f"rp_curves_{ds}.png").exists():
                parts.append(_figure(fig / f"rp_curves_{ds}.png", 1100))
        if not len(rp):
            parts.append("<p class='note'>No dataset with recurring-pattern ground truth.</p>")

    if counting is not None:
        tab = counting_compact(counting, decimals)
        parts.append("<h2 id='counting'>Counting</h2><p class='note'>Each ground-truth "
                     "pattern that a found pattern matches is counted by the matching pattern "
                     "with the most instances: count error and share of exact counts over them; "
                     "the same for each image's dominant pattern. Every column (counts over all "
                     f"matched patterns, pooled precision / recall) in {link('counting.tsv')}."
                     "</p>" + (tab.to_html() if tab is not None else
                               "<p class='note'>No dataset with recurring-pattern ground "
                               "truth.</p>"))

    if vpd is not None:
        parts.append("<h2 id='vp'>Vanishing points</h2><p class='note'>Share of images whose "
                     "vanishing point lies within a threshold of the ground truth (point error "
                     "in pixels, angle error of the VP direction in degrees); a missing VP "
                     "fails every threshold. The table picks three thresholds of each; the "
                     f"curves show all: {link('vpd.tsv')}, per image: {link('vpd_errors.tsv')}"
                     f", paired tests: {link('vpd_tests.tsv')}.</p>")
        for ds in _datasets([], vpd, order=names):
            tab = vp_compact(vpd, ds, vp_err, decimals)
            png = fig / f"vpd_{ds}.png"
            n = pd.to_numeric(vpd.loc[vpd["dataset"].astype(str) == ds, "n_images"]).max()
            parts.append(f"<h3>{html.escape(ds)}<span class='sub'>{_plural(n, 'image')} with "
                         "VP ground truth</span></h3><div class='pair'><div>"
                         + (tab.to_html() if tab is not None else "")
                         + _tests_details(vp_tests, ds) + "</div>"
                         + (f"<div class='fig'>{_figure(png, 640)}</div>" if png.exists()
                            else "")
                         + "</div>")
        if not len(vpd):
            parts.append("<p class='note'>No dataset with vanishing-point ground truth.</p>")

    if ts is not None:
        tab = ts_compact(ts, decimals)
        png = fig / "ts_sweep.png"
        parts.append("<h2 id='ts'>Translation symmetry</h2><p class='note'>SR_ts: share of "
                     "images with a pattern whose cross ratio lies within t of 4/3 (equal "
                     "spacing in 3D); TPR / FPR on ground-truth patterns with equal / unequal "
                     "spacing; flagged: images RESCU marks as TS. The curves sweep t over "
                     f"(0, 0.15] and (0, 1]: {link('ts.tsv')}.</p><div class='pair'><div>"
                     + (tab.to_html() if tab is not None else
                        "<p class='note'>No dataset with recurring-pattern ground truth.</p>")
                     + "</div>" + (f"<div class='fig'>{_figure(png, 640)}</div>"
                                   if png.exists() else "")
                     + "</div>")

    if samples:
        parts.append("<h2 id='pictures'>Pictures: what was found</h2><p class='note'>The "
                     "overlays of every image: the instances of each recurring pattern (one "
                     "colour per pattern, labelled), a legend with each pattern's count and "
                     "confidence, the supported vanishing points, the caption in the band "
                     "below; under each, the rectified views of its patterns. A click opens "
                     "the full picture.</p>")
        for ds in names:
            if ds not in by_ds:
                continue
            parts.append(f"<h3>{html.escape(ds)}</h3><div class='gallery'>")
            for s in by_ds[ds]:
                rect = "".join(img_tag(r, height=48) for r in s.rectified[:6])
                cap = (f"<div class='cap'>{html.escape(s.caption)}</div>"
                       if s.caption and s.caption != s.summary else "")
                parts.append(
                    f"<figure id='{s.anchor}'>"
                    f"{_full_link(s, out_html, img_tag(s.overlay, width=316, alt=s.image))}"
                    f"<figcaption><b>{html.escape(s.image)}</b>: {html.escape(s.summary)}"
                    + cap + (f"<div class='rect'>{rect}</div>" if rect else "")
                    + "</figcaption></figure>")
            parts.append("</div>")

    if abl is not None or abl2 is not None:
        parts.append("<h2 id='ablations'>Ablations</h2>")
        if abl is not None:
            parts.append("<h3>Stage I: which parameters are adaptive, orientation mode</h3>"
                         f"<p class='note'>All images; {link('ablation.tsv')}.</p>")
            for ds in _datasets([], abl, order=names):
                g = abl[abl["dataset"].astype(str) == ds]
                tab = summary_cells(g, ["adaptive"], decimals=decimals, alpha=alpha)
                parts.append(f"<p class='note'><b>{html.escape(ds)}</b></p>" + tab.to_html())
        if abl2 is not None:
            parts.append("<h3>Stage II: proposals and prediction</h3><p class='note'>All "
                         f"images; per subset in {link('stage2_ablation.tsv')}.</p>")
            for ds in _datasets([], abl2, order=names):
                g = abl2[abl2["dataset"].astype(str) == ds]
                if "subset" in g.columns:
                    g = g[g["subset"].astype(str) == "all"]
                tab = summary_cells(g, ["method"], decimals=decimals, alpha=alpha)
                parts.append(f"<p class='note'><b>{html.escape(ds)}</b></p>" + tab.to_html())

    if failures is not None or captions is not None:
        parts.append("<h2 id='diagnostics'>Failures and captions</h2>")
        if failures is not None:
            parts.append("<h3>Failures</h3>")
            parts.append("<p class='note'>No image failed.</p>" if not len(failures) else
                         plain_table(failures, decimals, wrap=["message"]).to_html())
        if captions is not None and len(captions):
            cap = captions.copy()
            if "image" in cap:
                cap["image"] = cap["image"].map(lambda p: Path(str(p)).name)
            tab = plain_table(cap, decimals, wrap=[c for c in ("base", "enhanced")
                                                   if c in cap]).to_html()
            parts.append(f"<h3>Captions</h3><details{' open' if len(cap) <= 20 else ''}>"
                         f"<summary>{len(cap)} images ({link('captions.tsv')})</summary>"
                         f"{tab}</details>")
    parts.append(f"<script>{CHECK_JS}</script></body></html>")
    with atomic_path(out_html) as tmp:
        tmp.write_text("\n".join(parts))


def _tests_details(tests: pd.DataFrame | None, ds: str) -> str:
    """The paired tests of one dataset's VP errors, folded."""
    if tests is None or not len(tests):
        return ""
    g = tests[tests["dataset"].astype(str) == ds].drop(columns="dataset")
    if g.empty:
        return ""
    g = g.assign(error=g["error"].map(lambda e: human_name(str(e)).lower()))
    tab = plain_table(g, 2)
    tab.cells["p_value"] = [_num(v, 3) for v in g["p_value"]]
    return (f"<details><summary>Paired tests of the errors ({len(g)})</summary>"
            f"{tab.to_html()}</details>")


def _summary_meta(summary_md: Path) -> str:
    """The line of ``summary.md`` that says what produced the tables (version, backbone),
    as HTML without Markdown syntax; the part that repeats the table legend is left out."""
    if not summary_md.exists():
        return ""
    lines = [x.strip() for x in summary_md.read_text().splitlines()]
    title = next((x.lstrip("# ") for x in lines if x.startswith("# ")), "")
    body = next((x for x in lines if x and not x.startswith("#")), "")
    body = body.split(" Metrics:")[0]
    title = title.split(":")[0]
    return md_inline(f"{title}. {body}" if title else body)


def build_run_report(out_html: str | Path, results: str | Path,
                     samples: Mapping[str, Sequence[str]],
                     evaluation: Mapping[str, Any] | None = None,
                     tables: Iterable[str | Path] | None = None,
                     report: Mapping[str, Any] | None = None,
                     skipped: Mapping[str, str] | None = None) -> None:
    """The report of a pipeline run from its results folder.

    ``samples`` maps each dataset to the image stems whose overlays are shown;
    ``report`` is the config's ``report`` section (``first_screen``: photos picked for
    the top, ``samples_per_dataset``: pictures beside each dataset's headline);
    ``evaluation`` is the config's ``evaluation`` section (``significance_alpha``,
    ``iod_h``, ``decimals``) for the notes and number formats; ``tables`` the table
    files the run made (default: all in ``<results>/tables``); ``skipped`` the configured
    datasets left out of the run, each with the reason (the report names them and says
    how to add a dataset).
    """
    from ..captions.caption import NO_PATTERN, pattern_confidence, summary_line
    from ..io import read_result

    results = Path(results)
    evaluation = evaluation or {}
    items = []
    for ds, stems in samples.items():
        for stem in stems:
            res = read_result(results / ds / "final" / f"{stem}.json")
            rect_dir = results / ds / "rectified" / stem
            rect = sorted(rect_dir.glob("*.png")) if rect_dir.is_dir() else []
            f = res.extra.get("failure")
            summary = line = summary_line(res)
            confs = [pattern_confidence(p)[1] for p in res.patterns if p.count >= 2]
            if f and f.get("degraded_to"):  # a step failed; the previous step's result kept
                summary += f" ({f.get('stage')} failed; {f.get('degraded_to')}'s result)"
            elif f:
                summary = f"failed in {f.get('stage')}: {f.get('message')}"
            items.append(Sample(ds, res.image or stem, results / ds / "overlay" / f"{stem}.png",
                                rect, summary, (res.caption or {}).get("enhanced", ""),
                                found=line != NO_PATTERN,
                                failed=bool(f) and not f.get("degraded_to"),
                                confidence=max(confs) if confs else None))
    build_report(out_html, results / "tables", results / "figures", items,
                 datasets=list(samples) or None,
                 meta=_summary_meta(results / "tables" / "summary.md"),
                 alpha=float(evaluation.get("significance_alpha", 0.05)),
                 iod_h=evaluation.get("iod_h"),
                 decimals=int(evaluation.get("decimals", 2)), tables=tables,
                 thumbs=int((report or {}).get("samples_per_dataset", 3)),
                 first_screen=int((report or {}).get("first_screen", 8)),
                 skipped=skipped)


# ----------------------------------------------------------------------------- the page as seen
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync")


def find_chromium() -> str | None:
    """The Chromium executable (``chromium``, ``chromium-browser``, ``google-chrome``), or
    None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


def _chromium(args: Sequence[str], timeout: float) -> subprocess.CompletedProcess:
    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError("no Chromium executable (apt-get install chromium)")
    with tempfile.TemporaryDirectory(prefix="rescu-chromium-") as profile:
        return subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args],
                              capture_output=True, text=True, timeout=timeout)


def chromium_screenshot(html_path: str | Path, png: str | Path, width: int = 1400,
                        height: int = 900, timeout: float = 120) -> Path:
    """Screenshot of the first ``width`` x ``height`` screen of the page, as a reader
    opening it in a window of that size sees it."""
    png = Path(png).resolve()
    png.parent.mkdir(parents=True, exist_ok=True)
    proc = _chromium([f"--window-size={width},{height}", f"--screenshot={png}",
                      Path(html_path).resolve().as_uri()], timeout)
    if not png.exists():
        raise RuntimeError(f"chromium wrote no screenshot ({proc.returncode}):\n"
                           f"{proc.stderr[-2000:]}")
    return png


def chromium_layout(html_path: str | Path, width: int = 1400, height: int = 900,
                    timeout: float = 120) -> dict[str, Any]:
    """The page's layout in a ``width`` x ``height`` window of headless Chromium: the
    JSON that the report's inline check script writes when opened with ``#check``
    (``innerWidth``, ``clientWidth``, ``scrollWidth`` of the page, ``tables`` with their
    boxes in page pixels, ``headline`` and ``firstImg`` boxes, ``imgsOnFirstScreen``)."""
    proc = _chromium([f"--window-size={width},{height}", "--dump-dom",
                      Path(html_path).resolve().as_uri() + "#check"], timeout)
    m = re.search(r'<pre id="layout-check"[^>]*>(.*?)</pre>', proc.stdout, re.S)
    if not m:
        raise RuntimeError(f"no layout in chromium's DOM ({proc.returncode}):\n"
                           f"{proc.stderr[-2000:]}")
    return json.loads(html.unescape(m.group(1)))


def first_screen_problems(layout: Mapping[str, Any], height: int = 900) -> list[str]:
    """What keeps the first screen of :func:`chromium_layout`'s page from reading well
    (empty: nothing): a page or table wider than the window, no picture or no photo
    caption (of the picked photos, at least 13 px) within the first ``height`` pixels
    (or the window's inner height, if less)."""
    problems = []
    width = layout["clientWidth"]
    screen = min(height, layout.get("innerHeight") or height)
    if layout["scrollWidth"] > width:
        problems.append(f"page {layout['scrollWidth']} px wide, window {width} px")
    for t in layout["tables"]:
        if t["right"] > width + 0.5 or t["scrollWidth"] > width:
            problems.append(f"table '{t['cls']}' reaches {t['right']:.0f} px "
                            f"({t['width']:.0f} px wide, window {width} px)")
    cap = layout.get("firstCaption")
    if not cap:
        problems.append("no photo caption")
    elif cap["bottom"] > screen:
        problems.append(f"the first photo's caption ends at {cap['bottom']:.0f} px, below "
                        f"the first screen ({screen} px)")
    elif layout.get("captionFontPx", 0) < 13:
        problems.append(f"photo captions in {layout.get('captionFontPx')} px type")
    if layout.get("imgsOnFirstScreen", 0) < 1:
        problems.append("no picture on the first screen")
    return problems
