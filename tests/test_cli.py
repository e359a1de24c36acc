"""The `rescu` command and the Python API, as a user meets them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from rescu.io import load_coco_rps, write_json

REPO = Path(__file__).resolve().parents[1]
RESCU = Path(sys.executable).parent / "rescu"


def rescu(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(RESCU), *args], capture_output=True, text=True, timeout=600)


def shelf_photo(path: Path, tins: bool = False) -> Path:
    """A photo from outside any dataset: five copies of one object on a shelf; with
    ``tins``, six round tins (34 px) on the floor below it as well."""
    import cv2

    rng = np.random.default_rng(7)
    img = np.full((300, 520, 3), (150, 120, 90), np.uint8)
    img += rng.integers(0, 12, img.shape, dtype=np.uint8)
    obj = rng.integers(0, 255, (10, 8, 3), dtype=np.uint8).repeat(7, 0).repeat(7, 1)
    for k in range(5):
        img[110:180, 30 + k * 95:86 + k * 95] = obj
    if tins:
        for k in range(6):
            c = (50 + k * 84, 245)
            cv2.circle(img, c, 17, (40, 60, 170), -1)
            cv2.circle(img, c, 9, (220, 210, 60), -1)
    Image.fromarray(img).save(path)
    return path


def test_help_explains_every_option():
    for args in (["--help"], ["discover", "--help"], ["evaluate", "--help"]):
        out = rescu(*args)
        assert out.returncode == 0 and "usage: rescu" in out.stdout
    text = rescu("discover", "--help").stdout
    for opt in ("--out", "--method", "--config", "--set", "--dense", "--objects", "--keep-work",
                "--quiet", "--overlay"):
        assert opt in text


def test_discover_on_own_photo_and_bad_file(tmp_path):
    photo = shelf_photo(tmp_path / "shelf.png")
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"\xff\xd8\xff garbage")
    out = rescu("discover", str(photo), str(bad), "--out", str(tmp_path / "out"),
                "--method", "rescu-i", "--quiet")
    assert out.returncode == 1, out.stderr  # one image failed, the other is done
    assert "shelf.png:" in out.stdout and "broken.jpg: FAILED in prepare" in out.stdout
    d = json.loads((tmp_path / "out" / "shelf.json").read_text())
    assert d["method"] == "rescu-i" and d["caption"]["enhanced"]
    assert max(p["count"] for p in d["patterns"]) == 5
    assert (tmp_path / "out" / "shelf.png").stat().st_size > 0
    assert json.loads((tmp_path / "out" / "broken.json").read_text())["failure"]["stage"] == "prepare"
    # the gallery: both photos, the overlay linked at full size, the failure said
    page = (tmp_path / "out" / "index.html").read_text()
    assert "Gallery: " in out.stdout and "href='shelf.png'" in page
    assert "data:image/jpeg;base64," in page and "failed in prepare" in page
    assert d["caption"]["enhanced"].replace("'", "&#x27;") in page


def test_discover_dense_adds_the_dense_source(tmp_path):
    # the five objects' random blocks give the dense source only sub-object specks (below
    # dense.min_object_px); the tins are what it finds
    photo = shelf_photo(tmp_path / "shelf.png", tins=True)
    # mode both: stage I's RPs first, every RP reported (mode objects, the default of
    # --dense, scores and may hide RPs: tests/test_objects.py)
    out = rescu("discover", str(photo), "--out", str(tmp_path / "out"), "--method", "rescu-i",
                "--dense", "--set", "dense.mode=both", "--quiet")
    assert out.returncode == 0, out.stderr
    d = json.loads((tmp_path / "out" / "shelf.json").read_text())
    n_dense = sum(p.get("source") == "dense" for p in d["patterns"])
    assert n_dense >= 1 and d["n_dense_patterns"] == n_dense
    # stage I's RP (the five objects) is still there, beside the dense ones
    assert max(p["count"] for p in d["patterns"] if p.get("source") != "dense") == 5


def test_discover_objects_profile(tmp_path):
    # --objects: only the dense source's RPs (stage I's five-object RP is not used)
    photo = shelf_photo(tmp_path / "shelf.png", tins=True)
    out = rescu("discover", str(photo), "--out", str(tmp_path / "out"), "--method", "rescu-i",
                "--objects", "--quiet")
    assert out.returncode == 0, out.stderr
    d = json.loads((tmp_path / "out" / "shelf.json").read_text())
    assert d["patterns"] and all(p.get("source") == "dense" for p in d["patterns"])
    # --set still applies over the profile: both sources again
    out = rescu("discover", str(photo), "--out", str(tmp_path / "both"), "--method", "rescu-i",
                "--objects", "--set", "dense.mode=both", "--quiet")
    assert out.returncode == 0, out.stderr
    d = json.loads((tmp_path / "both" / "shelf.json").read_text())
    assert max(p["count"] for p in d["patterns"] if p.get("source") != "dense") == 5


def test_objects_profile_loads_and_unknown_profile_is_refused():
    from rescu.config import load_config
    from rescu.io import InputError

    cfg = load_config(profile="objects", stage2=False)
    assert cfg["dense"]["enabled"] and cfg["dense"]["mode"] == "dense"
    # its RPs are all whole objects: stage II extends them with the default's gates for
    # whole objects (any proposal), so the profile needs no stage2 section of its own
    gates = cfg["stage2"]["predict"]["whole_objects"]
    assert gates["enabled"] and gates["lattice_only"] is False
    base = load_config(stage2=False)
    assert cfg["stage1"] == base["stage1"] and cfg["stage2"] == base["stage2"]
    with pytest.raises(InputError, match="unknown"):
        load_config(profile="facades", stage2=False)


def test_discover_usage_errors_exit_2(tmp_path):
    assert rescu("discover", str(tmp_path / "missing.jpg"), "--out", str(tmp_path)).returncode == 2
    photo = shelf_photo(tmp_path / "p.png")
    bad = rescu("discover", str(photo), "--out", str(tmp_path), "--set", "stage1.P_d=abc")
    assert bad.returncode == 2 and "stage1.P_d" in bad.stderr


def test_python_api(tmp_path):
    from rescu import discover

    res = discover(shelf_photo(tmp_path / "s.png"), method="rescu-i")
    assert max(p.count for p in res.patterns) == 5 and res.caption["enhanced"]


def test_evaluate_ground_truth_as_predictions_gives_one(tmp_path):
    from rescu.data.synth import SynthParams, generate_dataset
    from rescu.types import ImageResult, Instance, Pattern

    ds = tmp_path / "ds"
    generate_dataset(ds, SynthParams.from_dict({"n_images": 2, "sizes": [[480, 360]]}))
    preds = tmp_path / "preds"
    for fname, rps in load_coco_rps(ds / "annotations.json").items():
        res = ImageResult(image=fname, width=480, height=360, method="gt",
                          patterns=[Pattern(i, 1.0, [Instance(b) for b in rp.boxes])
                                    for i, rp in enumerate(rps)])
        write_json(preds / (Path(fname).stem + ".json"), res)
    out = rescu("evaluate", str(ds), str(preds), "--out", str(tmp_path / "scores"))
    assert out.returncode == 0, out.stderr
    summary = pd.read_csv(tmp_path / "scores" / "rp_discovery.tsv", sep="\t")
    for m in ("instance_precision", "instance_recall", "rp_precision", "rp_recall"):
        assert (summary[f"{m}_mean"] == 1.0).all(), m
    assert "1.00" in out.stdout


def test_slurm_profile_parses_in_dry_run(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("datasets: {photos: {enabled: false}, cmp_facade: {enabled: false}, "
                   "spb_facades: {enabled: false}, chess: {enabled: false}, "
                   "aerial_cars: {enabled: false}, york_urban: {enabled: false}}\n"
                   "synthetic: {n_images: 2}\n")
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s",
                           str(REPO / "Snakefile"), "--directory", str(tmp_path),
                           "--configfile", str(cfg), "--profile",
                           str(REPO / "profiles" / "slurm"), "-n"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "stage2_features" in proc.stdout + proc.stderr


def test_a_failed_photo_is_a_message_card_in_the_gallery(tmp_path):
    """A broken file's card holds the message, not its (1-pixel-wide) overlay."""
    import re

    folder = tmp_path / "photos"
    folder.mkdir()
    shelf_photo(folder / "good.png")
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    out = tmp_path / "out"
    proc = rescu("discover", str(folder), "--out", str(out), "--method", "rescu-i", "--quiet")
    assert proc.returncode == 1, proc.stderr
    page = (out / "index.html").read_text()
    cards = re.findall(r"<figure>(.*?)</figure>", page)
    broken = [c for c in cards if "broken.png" in c]
    good = [c for c in cards if "good.png" in c]
    assert len(broken) == 1 and len(good) == 1
    assert "failcard" in broken[0] and "<img" not in broken[0]
    assert "unreadable or truncated" in broken[0] or "not an image" in broken[0]
    assert "<img" in good[0]
    assert "max-height:600px" in page


@pytest.mark.parametrize("args, needle", [
    (["discover", "x.png", "--ouput", "o"], "unrecognized argument '--ouput' (did you mean --out?)"),
    (["discover", "--methd", "rescu-i", "x.png", "--out", "o"],
     "unrecognized argument '--methd' (did you mean --method?)"),
    (["discover", "x.png"], "the following arguments are required: --out"),
])
def test_a_mistyped_option_is_named_by_its_subcommand(args, needle):
    proc = rescu(*args)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("rescu discover: error: ") and needle in last, proc.stderr


def test_evaluate_names_its_threshold_iod_and_keeps_h(tmp_path):
    from rescu import cli

    p = cli.build_parser()
    assert cli._parse(p, ["evaluate", "d", "p", "--iod", "0.3"]).h == 0.3
    assert cli._parse(p, ["evaluate", "d", "p", "--h", "0.4"]).h == 0.4
    assert "--iod H" in rescu("evaluate", "--help").stdout


def test_the_log_says_what_ran_and_subfolders_are_named(tmp_path):
    folder = tmp_path / "photos"
    (folder / "more").mkdir(parents=True)
    shelf_photo(folder / "a.png")
    shelf_photo(folder / "more" / "b.png")
    out = tmp_path / "out"
    proc = rescu("discover", str(folder), "--out", str(out), "--method", "rescu-i", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "not searched, the subfolder(s)" in proc.stderr and "more" in proc.stderr
    log = (out / "rescu.log").read_text()
    assert "rescu discover: 1 photo(s), method rescu-i" in log
    assert "a.png: " in log and "1 of 1 image(s) done" in log
