"""The report's first screen as a reader sees it: a headless-Chromium screenshot of
``index.html`` in a 1400 x 900 window, and a check of its layout (no table wider than
the window, the headline table and a picture on the first screen).

    python benchmarks/speed/report_screenshot.py results/report/index.html docs/report-first-screen.png

Needs Chromium (Debian: ``apt-get install chromium``). Exits 1 when the layout check
fails, 2 when Chromium is missing.
"""

from __future__ import annotations

import argparse
import json
import sys

from rescu.evaluation.report import (chromium_layout, chromium_screenshot, find_chromium,
                                     first_screen_problems)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("html", help="the report (results/report/index.html)")
    ap.add_argument("png", help="where the screenshot goes")
    ap.add_argument("--width", type=int, default=1400)
    ap.add_argument("--height", type=int, default=900)
    a = ap.parse_args(argv)
    if find_chromium() is None:
        print("no Chromium: apt-get install chromium", file=sys.stderr)
        return 2
    png = chromium_screenshot(a.html, a.png, a.width, a.height)
    layout = chromium_layout(a.html, a.width, a.height)
    problems = first_screen_problems(layout, a.height)
    widest = max((t["width"] for t in layout["tables"]), default=0)
    print(json.dumps({"screenshot": str(png), "window": [layout["innerWidth"],
                      layout["innerHeight"]], "page_width": layout["scrollWidth"],
                      "tables": len(layout["tables"]), "widest_table": round(widest),
                      "headline_bottom": (layout.get("headline") or {}).get("bottom"),
                      "pictures_on_first_screen": layout.get("imgsOnFirstScreen"),
                      "problems": problems}, indent=1))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
