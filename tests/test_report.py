"""The HTML report as a reader meets it: headline figures per dataset beside pictures,
human column names, no Markdown syntax, long sweeps as a curve and a TSV link; and, in
headless Chromium where it is installed, a first 1400 x 900 screen that shows the
headline table and a picture with no table wider than the window.

Every input is a tiny fake results folder built here (no pipeline run)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from rescu.evaluation import core as E
from rescu.evaluation import vpd as EV
from rescu.evaluation import report as R
from rescu.evaluation import report_tables as RT

METRICS = list(RT.RP_METRICS)
CHROMIUM = shutil.which("chromium") or R.find_chromium()


# ----------------------------------------------------------------------------- fake run
def rp_scores(datasets=("synthetic", "cmp_facade"), n=4, seed=0) -> pd.DataFrame:
    """Per-image scores of GRASP, RESCU-I, RESCU-II (RESCU-II best)."""
    rng = np.random.default_rng(seed)
    rows = []
    for ds in datasets:
        for i in range(n):
            for m, base in (("GRASP", 0.5), ("RESCU-I", 0.7), ("RESCU-II", 0.9)):
                r = {"dataset": ds, "image": f"images/{ds}_{i}.png", "method": m,
                     "subset": "frontal" if i % 2 else "projective"}
                r.update({k: float(np.clip(base + rng.normal(0, 0.05), 0, 1)) for k in METRICS})
                rows.append(r)
    return pd.DataFrame(rows)


def vp_errors(datasets=("synthetic", "york_urban"), n=5) -> pd.DataFrame:
    rows = []
    for ds in datasets:
        for i in range(n):
            for k, m in enumerate(("RESCU (AC)", "LSD lines")):
                missing = m == "LSD lines" and i == 0
                rows.append({"dataset": ds, "image": f"images/{ds}_{i}.png", "method": m,
                             "vp_missing": missing,
                             "point_error_px": np.inf if missing else 3.0 + 10 * i + 30 * k,
                             "angle_error_deg": np.inf if missing else 1.0 + i + 4 * k,
                             "focal_px": 500.0, "focal_source": "true", "n_gt_vps": 3})
    return pd.DataFrame(rows)


def write_png(path: Path, w: int, h: int, colour=(200, 120, 40)) -> Path:
    img = np.full((h, w, 3), 245, np.uint8)
    cv2.rectangle(img, (w // 8, h // 8), (w // 3, h // 3), colour, 3)
    cv2.rectangle(img, (w // 2, h // 2), (w - w // 8, h - h // 8), colour, 3)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)
    return path


def fake_results(root: Path, paper: bool = True) -> tuple[Path, dict[str, list[str]]]:
    """A results folder as a run leaves it: tables/, figures/ and per image final JSON,
    overlay and rectified views; datasets with RP truth (synthetic, cmp_facade), VP
    truth only (york_urban) and none (photos)."""
    res = root / "results"
    t, fig = res / "tables", res / "figures"
    t.mkdir(parents=True)
    scores = rp_scores()
    E.write_tsv(E.summary_table(scores, METRICS), t / "rp_discovery.tsv")
    E.write_tsv(scores, t / "rp_scores.tsv")
    errors = vp_errors()
    E.write_tsv(errors, t / "vpd_errors.tsv")
    E.write_tsv(EV.vp_success_table(errors), t / "vpd.tsv")
    E.write_tsv(EV.vp_significance(errors), t / "vpd_tests.tsv")
    ts = []
    for sweep, ts_ in (("fine", np.round(np.arange(1, 16) * 0.01, 2)),
                       ("coarse", np.round(np.arange(1, 21) * 0.05, 2))):
        for t_ in ts_:
            ts.append({"dataset": "synthetic", "method": "RESCU-II", "t": t_,
                       "sr_ts": min(1.0, 5 * t_), "n_images": 4, "sr_ts_flag": 0.75,
                       "tpr": min(1.0, 6 * t_), "n_equal": 3, "fpr": min(1.0, t_),
                       "n_unequal": 2, "sweep": sweep})
    E.write_tsv(pd.DataFrame(ts), t / "ts.tsv")
    counting = pd.DataFrame([
        {"dataset": ds, "method": m, "n_images": 4, "n_matched": 6, "count_mae": mae,
         "exact_rate": ex, "n_matched_rps": 7, "count_mae_all_rps": mae + 0.5,
         "exact_rate_all_rps": ex - 0.1, "n_dominant": 4, "dominant_matched_rate": 1,
         "dominant_count_mae": mae, "dominant_exact_rate": ex, "instance_precision": 0.9,
         "instance_recall": 0.8, "rp_precision": 0.9, "rp_recall": 0.8,
         "instance_precision_pooled": 0.9, "instance_recall_pooled": 0.8}
        for ds in ("synthetic", "cmp_facade")
        for m, mae, ex in (("RESCU-I", 1.5, 0.5), ("RESCU-II", 0.25, 0.75))])
    E.write_tsv(counting, t / "counting.tsv")
    samples: dict[str, list[str]] = {}
    caps, fails = [], []
    for ds in ("synthetic", "photos", "cmp_facade", "york_urban"):
        samples[ds] = []
        for i in range(4):
            stem = f"{ds}_{i}"
            failed = ds == "photos" and i == 3
            d = {"image": f"images/{stem}.png", "width": 480, "height": 424,
                 "method": "rescu-ii", "patterns": [], "dominant_pattern": None,
                 "vanishing_point": None,
                 "caption": {"base": "A row of windows.",
                             "enhanced": f"Four windows in a row ({stem})."}}
            if failed:
                d["failure"] = {"stage": "stage2", "type": "RuntimeError",
                                "message": "no proposals " * 12}
                fails.append({"dataset": ds, "image": d["image"], "stage": "stage2",
                              "type": "RuntimeError", "message": "no proposals " * 12})
            (res / ds / "final").mkdir(parents=True, exist_ok=True)
            (res / ds / "final" / f"{stem}.json").write_text(json.dumps(d))
            write_png(res / ds / "overlay" / f"{stem}.png", 480, 424 + 40 * (i % 2))
            write_png(res / ds / "rectified" / stem / "rp0.png", 300, 100)
            caps.append({"dataset": ds, "image": d["image"], "n_patterns": i % 3,
                         "dominant_count": 4 * (i % 3), "base": "A row of windows.",
                         "enhanced": "Four windows in a row, next to other repeated items, "
                                     "with a vanishing point outside of the image."})
            if i < 3:
                samples[ds].append(stem)
    E.write_tsv(pd.DataFrame(caps), t / "captions.tsv")
    E.write_tsv(pd.DataFrame(fails, columns=["dataset", "image", "stage", "type", "message"]),
                t / "failures.tsv")
    if paper:
        abl = E.summary_table(scores.assign(subset=np.nan).replace(
            {"method": {"GRASP": "none", "RESCU-I": "P_d", "RESCU-II": "all"}}), METRICS)
        E.write_tsv(abl.rename(columns={"method": "adaptive"}), t / "ablation.tsv")
        s2 = E.summary_table(scores.replace({"method": {"GRASP": "RESCU-II[edgeboxes]"}}),
                             METRICS)
        E.write_tsv(s2, t / "stage2_ablation.tsv")
    (t / "summary.md").write_text(
        "# RESCU 0.1.0: tables\n\nStage-II backbone: **efficientnet-lite0** (frozen, "
        "ImageNet weights). Metrics: IOD protocol of `rescu.evaluation.metrics`; mean ± std over "
        "images; bold = best.\n")
    for ds in ("synthetic", "cmp_facade"):
        write_png(fig / f"rp_curves_{ds}.png", 1920, 408)
    for ds in ("synthetic", "york_urban"):
        write_png(fig / f"vpd_{ds}.png", 1080, 432)
    write_png(fig / "ts_sweep.png", 1000, 400)
    return res, samples


@pytest.fixture
def run(tmp_path):
    res, samples = fake_results(tmp_path)
    out = res / "report" / "index.html"
    R.build_run_report(out, res, samples, {"significance_alpha": 0.05, "iod_h": 0.5})
    return res, out, out.read_text()


def visible_text(page: str) -> str:
    """The page's text as a reader sees it (tags, scripts, styles and pictures out)."""
    page = re.sub(r"<(script|style)\b.*?</\1>", "", page, flags=re.S)
    return re.sub(r"<[^>]+>", " ", page)


# ----------------------------------------------------------------------------- building blocks
def test_human_names():
    assert RT.human_name("instance_precision_mean") == "Instance precision (mean)"
    assert RT.human_name("instance_precision_std") == "Instance precision (std)"
    assert RT.human_name("rp_recall_p_vs_best") == "RP recall, p vs best"
    assert RT.human_name("count_mae") == "Count error (MAE)"
    assert RT.human_name("n_images") == "Images"
    assert RT.human_name("n_widgets") == "Number of widgets"   # a column not named yet
    assert RT.human_name("sr_ts_at_max") == "SR TS at max"
    assert RT.human_name("≤ 5 px") == "≤ 5 px"                 # already human


def test_md_inline_leaves_no_markdown():
    s = RT.md_inline("backbone: **efficientnet-lite0** of `rescu.evaluation.metrics`, _not_ <b>")
    assert s == ("backbone: <b>efficientnet-lite0</b> of <code>rescu.evaluation.metrics</code>, "
                 "<i>not</i> &lt;b&gt;")
    assert "**" not in RT.md_inline("a ** b **c")


def test_rp_headline_rows_cells_and_bold():
    summary = E.summary_table(rp_scores(), METRICS)
    t = RT.rp_headline(summary, "synthetic")
    assert list(t.cells["method"]) == ["RESCU-II", "RESCU-I", "GRASP"]
    assert list(t.cells.columns) == ["method", *METRICS, "n_images"]
    row = summary[(summary["dataset"] == "synthetic") & (summary["subset"] == "all")
                  & (summary["method"] == "RESCU-II")].iloc[0]
    assert t.cells.iloc[0]["rp_recall"] == \
        f"{row['rp_recall_mean']:.2f} ± {row['rp_recall_std']:.2f}"
    assert t.cells.iloc[0]["n_images"] == "4"
    assert t.bold[METRICS].iloc[0].all() and not t.bold[METRICS].iloc[1:].any().any()
    page = t.to_html()
    assert page.count("<b>") == 4 and "table class=\"t headline\"" in page
    assert ">Instance P<" in page and ">RP R<" in page and ">Images<" in page
    assert RT.rp_headline(summary, "york_urban") is None


def test_ties_are_all_bold_and_italics_mark_no_significant_difference():
    df = pd.DataFrame({"dataset": ["d"] * 3, "subset": ["all"] * 3,
                       "method": ["A", "B", "C"], "n_images": [5, 5, 5],
                       "rp_recall_mean": [0.9, 0.9004, 0.5], "rp_recall_std": [0.1, 0.1, 0.2],
                       "rp_recall_p_vs_best": [np.nan, 0.8, 0.01]})
    t = RT.summary_cells(df, ["method"], metrics=["rp_recall"], alpha=0.05)
    assert list(t.bold["rp_recall"]) == [True, True, False]
    assert list(t.italic["rp_recall"]) == [False, False, False]
    df.loc[2, "rp_recall_p_vs_best"] = 0.3
    t = RT.summary_cells(df, ["method"], metrics=["rp_recall"], alpha=0.05)
    assert list(t.italic["rp_recall"]) == [False, False, True]
    # a rate read back as an integer column still shows two decimals
    assert RT.mean_std(1, 0) == "1.00 ± 0.00" and RT.mean_std(np.nan, 0.1) == "–"


def test_vp_and_found_headlines():
    errors = vp_errors()
    success = EV.vp_success_table(errors)
    t = RT.vp_headline(success, "york_urban", errors)
    assert list(t.cells["method"]) == ["RESCU (AC)", "LSD lines"]
    assert {"VP within 5 px", "VP within 5°", "Median angle error (°)"} <= set(t.cells.columns)
    assert t.cells.iloc[0]["VP within 5 px"] == "0.20"   # 1 of 5 images within 5 px
    assert t.bold.iloc[0]["Median angle error (°)"] and \
        not t.bold.iloc[1]["Median angle error (°)"]  # lower is better
    caps = pd.DataFrame({"dataset": ["photos"] * 3, "n_patterns": [0, 2, 3],
                         "dominant_count": [0, 6, 8]})
    t = RT.found_headline(caps, "photos")
    assert t.cells.iloc[0].to_dict() == {"Images": "3", "With a pattern": "2",
                                         "Patterns per image (median)": "2.0",
                                         "Dominant count (median)": "7.0"}


def test_a_peer_that_could_not_run_says_not_run():
    errors = vp_errors()
    peer = errors[errors["method"] == "LSD lines"].assign(
        method="lu-vp-detect (true focal)", vp_missing=True, point_error_px=np.inf,
        angle_error_deg=np.inf)
    errors = pd.concat([errors, peer], ignore_index=True)
    t = RT.vp_compact(EV.vp_success_table(errors), "synthetic", errors)
    row = t.cells[t.cells["method"] == "lu-vp-detect (true focal)"].iloc[0]
    assert (row.drop(["method", "Without a VP"]) == "not run").all()
    assert row["Without a VP"] == "5"
    ran = t.cells[t.cells["method"] == "LSD lines"].iloc[0]
    assert "not run" not in ran.tolist()


def test_long_tables_are_compact():
    errors = vp_errors()
    success = EV.vp_success_table(errors)     # 2 methods x 2 kinds x 7 thresholds
    t = RT.vp_compact(success, "synthetic", errors)
    assert len(t.cells) == 2
    assert [c for c in t.cells.columns if c.startswith("≤")] == \
        ["≤ 5 px", "≤ 30 px", "≤ 100 px", "≤ 1°", "≤ 5°", "≤ 20°"]
    # a missing VP counts as an infinite error: median of 6, 7, 8, 9, inf
    assert t.cells.iloc[1]["Median angle error (°)"] == "8.00"
    assert t.cells.iloc[1]["Without a VP"] == "1"
    rows = [{"dataset": "d", "method": "RESCU-II", "t": t_, "sr_ts": t_, "n_images": 3,
             "sr_ts_flag": 0.5, "tpr": np.nan, "n_equal": 0, "fpr": np.nan, "n_unequal": 0,
             "sweep": s} for s in ("fine", "coarse") for t_ in (0.01, 0.05, 0.1, 0.15)]
    t = RT.ts_compact(pd.DataFrame(rows))
    assert len(t.cells) == 1
    assert list(t.cells.columns) == ["dataset", "method", "Flagged as TS", "SR_ts at t = 0.05",
                                     "SR_ts at t = 0.1", "n_images"]   # no TPR/FPR: no truth


def test_report_page(run):
    res, out, page = run
    text = visible_text(page)
    assert "**" not in page and "efficientnet-lite0" in text
    for raw in ("instance_precision_mean", "instance_precision_std", "_p_vs_best",
                "n_images", "count_mae", "success_rate", "sr_ts_flag"):
        assert raw not in text, raw
    for human in ("Instance precision", "Count error (MAE)", "Exact count rate",
                  "Flagged as TS", "Dominant count"):
        assert human in text, human
    # real photos come first (8 picks, none from the synthetic benchmark, each a link to
    # its full-size picture), then the headline per dataset with pictures, synthetic last
    first_h2 = page.index("<h2")
    photos = page[page.index("id='photos'"):page.index("</section>")]
    assert photos.count("<img") == 8 and "synthetic" not in photos
    assert "href='../photos/overlay/photos_0.png'" in photos
    assert page[:first_h2].count("table class=\"t headline\"") == 4
    assert page[:first_h2].count("<img") == 8 + 4 * 3
    assert page.index("id='photos'") < page.index("id='ds-photos'") \
        < page.index("id='ds-york_urban'") < page.index("id='ds-synthetic'")
    york = page[page.index("id='ds-york_urban'"):page.index("</section>",
                                                             page.index("id='ds-york_urban'"))]
    assert "VP within 5 px" in york and "vanishing-point ground truth" in york
    photos = page[page.index("id='ds-photos'"):]
    assert "no ground truth" in photos[:2000] and "With a pattern" in photos[:2000]
    # long per-threshold tables: a curve and a link, not rows
    assert "href=\"../tables/vpd.tsv\"" in page and "href=\"../tables/ts.tsv\"" in page
    assert "≤ 10 px" not in text and "0.07" not in visible_text(
        page[page.index("id='ts'"):page.index("id='pictures'")])
    assert (res / "tables" / "vpd.tsv").exists()
    # sections in reading order; the ablations and diagnostics below
    order = [page.index(f"<h2 id='{a}'") for a in
             ("rp", "counting", "vp", "ts", "pictures", "ablations", "diagnostics")]
    assert order == sorted(order)
    assert "no proposals" in text                    # the failure is listed
    assert page.count("<table") == len(re.findall(r"<table class=\"t", page))


def test_pick_photos_leads_with_confident_results_and_a_failure():
    def sample(ds, i, conf=None, found=True, failed=False):
        return R.Sample(ds, f"images/{ds}_{i}.png", Path("x.png"), found=found,
                        failed=failed, confidence=conf)

    pool = ([sample("synthetic", i, 0.99) for i in range(3)]
            + [sample("cmp_facade", i, 0.1 * i) for i in range(5)]
            + [sample("chess", i, 0.05 * i) for i in range(3)]
            + [sample("photos", 0, found=False), sample("photos", 1, 0.9, failed=True)])
    picks = R.pick_photos(pool, 5)
    assert [Path(p.image).stem for p in picks] == [
        "cmp_facade_4", "chess_2", "cmp_facade_3", "chess_1", "photos_0"]
    assert R.pick_photos(pool[:3], 2)[0].dataset == "synthetic"  # only a benchmark: it
    assert R.pick_photos(pool, 0) == []


def test_report_without_paper_tables(tmp_path):
    res, samples = fake_results(tmp_path, paper=False)
    out = res / "report" / "index.html"
    R.build_run_report(out, res, samples)
    page = out.read_text()
    assert "id='ablations'" not in page and "Ablations" not in page
    assert "<h2 id='rp'" in page and "IOD protocol" in page  # no iod_h given


def test_report_names_the_datasets_the_run_skipped_and_how_to_add_one(tmp_path):
    res, samples = fake_results(tmp_path, paper=False)
    out = res / "report" / "index.html"
    R.build_run_report(out, res, samples, skipped={
        "chess": "folder ../shared/data/chess not found", "mine": "no images in /d/<x>"})
    page = out.read_text()
    note = page[page.index("Not in this run"):]
    note = note[:note.index("</p>")]
    assert "<b>chess</b> (folder ../shared/data/chess not found)" in note
    assert "<b>mine</b> (no images in /d/&lt;x&gt;)" in note      # escaped
    assert "<code>datasets</code>" in note and "Your own photos" in note
    assert page.index("id='photos'") < page.index("Not in this run")
    R.build_run_report(out, res, samples, skipped={})
    assert "Not in this run" not in out.read_text()


def test_report_shows_only_the_tables_the_run_made(tmp_path):
    """Ablation tables an earlier `paper` run left in the folder stay out of a default
    run's report (the pipeline names the tables it made)."""
    res, samples = fake_results(tmp_path, paper=True)
    made = [p for p in (res / "tables").glob("*.tsv") if "ablation" not in p.name]
    out = res / "report" / "index.html"
    R.build_run_report(out, res, samples, tables=made)
    page = out.read_text()
    assert "id='ablations'" not in page and "id='rp'" in page and "id='diagnostics'" in page


# ----------------------------------------------------------------------------- in a browser
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (Debian: apt-get "
                    "install chromium); the report's first screen is checked in it")
def test_first_screen_in_chromium(run, tmp_path):
    _, out, _ = run
    layout = R.chromium_layout(out, 1400, 900)
    assert layout["innerWidth"] == 1400
    assert R.first_screen_problems(layout, 900) == []
    assert layout["firstCaption"]["bottom"] < 900 and layout["imgsOnFirstScreen"] >= 3
    assert layout["captionFontPx"] >= 14
    assert len(layout["tables"]) >= 10
    assert all(t["right"] <= layout["clientWidth"] for t in layout["tables"])
    png = R.chromium_screenshot(out, tmp_path / "first-screen.png", 1400, 900)
    img = cv2.imread(str(png))
    assert img.shape[:2] == (900, 1400) and img.std() > 10   # a page, not a blank


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed")
def test_the_readme_screenshot_command_works(run, tmp_path, capsys):
    """The command that makes the README's picture (docs/results.md, "Speed and memory"):
    a screenshot of the report's first screen and its layout check, exit 0."""
    import importlib.util

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "speed" / "report_screenshot.py"
    spec = importlib.util.spec_from_file_location("report_screenshot", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    _, out, _ = run
    png = tmp_path / "shot.png"
    assert mod.main([str(out), str(png)]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["problems"] == [] and got["pictures_on_first_screen"] >= 3
    img = cv2.imread(str(png))
    assert img.shape[:2] == (900, 1400) and img.std() > 10


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed")
def test_the_check_notices_a_wide_table(tmp_path):
    """The layout check is not blind: a table wider than the window is reported."""
    page = tmp_path / "wide.html"
    cells = "".join(f"<td>very_long_column_name_{i}</td>" for i in range(40))
    page.write_text(f"<!doctype html><html><body><table class='t headline'><tr>{cells}</tr>"
                    f"</table><script>{R.CHECK_JS}</script></body></html>")
    problems = R.first_screen_problems(R.chromium_layout(page, 1400, 900), 900)
    assert any("wide" in p for p in problems) and "no picture on the first screen" in problems
