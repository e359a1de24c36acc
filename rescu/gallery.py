"""A page to browse what ``rescu discover`` found: ``<out>/index.html``.

:func:`write_gallery` reads the per-photo results of an output folder (``<name>.json``
beside ``<name>.png``) and writes one self-contained HTML page (pictures embedded as
JPEG, no script, no network) that opens from a file browser: per photo its overlay
picture (a click opens the full-size PNG beside the page), the one-line summary (counts,
confidence, the supported claims), the caption; a photo that failed gets a message card
in place of its picture (no picture is taller than 600 pixels on the page).
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Sequence

from .io import atomic_path, read_result

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;
 color:#1d1d1f;margin:0 auto;padding:12px 20px 40px;max-width:1400px;line-height:1.4}
h1{font-size:24px;margin:4px 0}
.lead{font-size:15px;color:#333}
.grid{display:flex;flex-wrap:wrap;gap:18px;margin-top:12px}
figure{margin:0;width:420px;max-width:100%}
figure img{max-width:100%;max-height:600px;height:auto;object-fit:contain;border:1px solid #ccc}
.failcard{box-sizing:border-box;width:100%;min-height:120px;padding:14px;border:1px solid #d99;
 background:#fff4f4;color:#a00;font-size:14px;overflow-wrap:anywhere}
figcaption{font-size:15px}
figcaption .name{font-weight:600}
figcaption .found{color:#333;font-size:14px}
figcaption .cap{font-style:italic;margin-top:2px}
.failed{color:#a00}
"""


def write_gallery(out_dir: str | Path, names: Sequence[str] | None = None,
                  title: str = "RESCU: what was found") -> Path:
    """Write ``<out_dir>/index.html`` for the results in ``out_dir``.

    Parameters
    ----------
    out_dir : path
        A ``rescu discover`` output folder.
    names : sequence of str, optional
        The result names (``<name>.json``) in page order; default: every JSON of the
        folder but ``rescu.log``'s neighbours, sorted.
    title : str
        The page title.

    Returns
    -------
    Path
        The page written (atomically).
    """
    from .captions.caption import NO_PATTERN, summary_line
    from .pages import img_tag

    out_dir = Path(out_dir)
    if names is None:
        names = sorted(p.stem for p in out_dir.glob("*.json"))
    cards, n_rp, n_failed = [], 0, 0
    for name in names:
        try:
            res = read_result(out_dir / f"{name}.json")
        except Exception:  # noqa: BLE001 - one unreadable result must not stop the page
            continue
        f = res.extra.get("failure")
        line = summary_line(res)
        if f and not f.get("degraded_to"):
            n_failed += 1
            found = (f"<span class='failed'>failed in {html.escape(str(f.get('stage')))}: "
                     f"{html.escape(str(f.get('message')))}</span>")
        else:
            n_rp += line != NO_PATTERN
            found = html.escape(line)
            if f:
                found += (f" <span class='failed'>({html.escape(str(f.get('stage')))} "
                          f"failed; {html.escape(str(f.get('degraded_to')))}'s result)</span>")
        cap = (res.caption or {}).get("enhanced") or ""
        png = out_dir / f"{name}.png"
        if f and not f.get("degraded_to"):  # a message card, whatever its overlay's size
            pic = (f"<div class='failcard'>could not be processed: "
                   f"{html.escape(str(f.get('message')))}</div>")
        else:
            pic = (f"<a href='{html.escape(png.name)}' title='full size'>"
                   f"{img_tag(png, width=420, alt=name)}</a>" if png.exists() else "")
        cards.append(
            f"<figure>{pic}<figcaption><div class='name'>{html.escape(Path(res.image).name or name)}"
            f"</div><div class='found'>{found}</div>"
            + (f"<div class='cap'>{html.escape(cap)}</div>" if cap and cap != line else "")
            + "</figcaption></figure>")
    lead = (f"{len(cards)} photo{'s' if len(cards) != 1 else ''}: {n_rp} with recurring "
            f"patterns, {len(cards) - n_rp - n_failed} without"
            + (f", {n_failed} failed" if n_failed else "")
            + ". Click a picture for its full size; per photo the JSON result beside it.")
    page = ("<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            "<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>"
            f"<h1>{html.escape(title)}</h1><p class='lead'>{html.escape(lead)}</p>"
            f"<div class='grid'>{''.join(cards)}</div></body></html>")
    path = out_dir / "index.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page)
    return path
