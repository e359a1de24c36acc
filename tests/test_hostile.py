"""Hostile input, round 3: links planted in an output folder, a user's own ``rescu.log``
and ``index.html``, concurrent runs on one folder, a FIFO for the manifest. Each gives a
clear refusal or correct behaviour, and nothing outside the output folder changes."""

from __future__ import annotations

import json
import multiprocessing
import os
from pathlib import Path

import pytest

from rescu import outputs
from rescu.io import InputError
from test_cli import rescu, shelf_photo
from test_trust import assert_one_line_error, checksums


@pytest.fixture
def photo(tmp_path: Path) -> Path:
    folder = tmp_path / "photos"
    folder.mkdir()
    return shelf_photo(folder / "shelf.png")


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A folder outside the output folder with a file and a dead process's 'staging'."""
    d = tmp_path / "outside"
    (d / "999999999-x").mkdir(parents=True)
    (d / "999999999-x" / "keep.txt").write_text("mine")
    (d / "precious.txt").write_text("do not truncate")
    return d


def _discover(photo: Path, out: Path, *more: str):
    return rescu("discover", str(photo), "--out", str(out), "--method", "rescu-i",
                 "--quiet", *more)


@pytest.mark.parametrize("link", ["rescu.log", "index.html", ".rescu-work", ".rescu-lock"])
def test_a_link_in_the_output_folder_is_refused_and_not_followed(photo, tmp_path, outside,
                                                                 link):
    out = tmp_path / "out"
    out.mkdir()
    target = outside if link == ".rescu-work" else outside / "precious.txt"
    os.symlink(target, out / link)
    before = checksums(outside)
    proc = _discover(photo, out)
    assert_one_line_error(proc, link)
    assert checksums(outside) == before and (outside / "999999999-x").is_dir()
    proc = _discover(photo, out, "--force")      # forced or not: never through a link
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert checksums(outside) == before


def test_keep_work_through_a_linked_folder_is_refused(photo, tmp_path, outside):
    out = tmp_path / "out"
    (out / ".work").mkdir(parents=True)
    os.symlink(outside, out / ".work" / "shelf")
    before = checksums(outside)
    proc = _discover(photo, out, "--keep-work")
    assert proc.returncode == 2 and "symbolic link" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert checksums(outside) == before


@pytest.mark.parametrize("own", ["rescu.log", "index.html"])
def test_a_users_own_log_or_page_is_not_replaced(photo, tmp_path, own):
    out = tmp_path / "out"
    out.mkdir()
    (out / own).write_text("my notes")
    proc = _discover(photo, out)
    assert_one_line_error(proc, own, "not written by rescu")
    assert (out / own).read_text() == "my notes"
    assert _discover(photo, out, "--force").returncode == 0   # forced: replaced
    assert _discover(photo, out).returncode == 0              # rescu's own now: a rerun
    assert "shelf" in (out / "index.html").read_text()


def test_the_gallery_lists_every_photo_of_the_folder(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    a = shelf_photo(folder / "a.png")
    b = shelf_photo(folder / "b.png", tins=True)
    out = tmp_path / "out"
    assert _discover(a, out).returncode == 0
    assert _discover(b, out).returncode == 0
    page = (out / "index.html").read_text()
    assert "a.png" in page and "b.png" in page


def test_a_fifo_as_the_manifest_is_refused_not_waited_on(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / outputs.MANIFEST)
    with pytest.raises(InputError, match="not a regular file"):
        outputs.read_manifest(out)


@pytest.mark.parametrize("manifest", [
    {"files": []}, [], {"results": {"x": {"files": []}}},
    {"results": {"x": {"files": {"x.json": "abc"}}}}, {"results": {}, "own": []}])
def test_a_malformed_manifest_is_one_line_naming_it(tmp_path, manifest):
    out = tmp_path / "out"
    out.mkdir()
    (out / outputs.MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"\.rescu-results\.json: not rescu's manifest"):
        outputs.read_manifest(out)


# ----------------------------------------------------------------- concurrent runs
def _commit_many(out: str, who: str, n: int) -> None:
    for i in range(n):
        with outputs.staging(out) as staged:
            (staged / f"{who}{i}.json").write_text(json.dumps({"who": who, "i": i}))
            outputs.commit(out, f"{who}{i}", staged, f"{who}{i}.png")


def test_two_runs_on_one_folder_keep_every_result(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_commit_many, args=(str(out), who, 40)) for who in "ab"]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    names = outputs.read_manifest(out)["results"]
    assert len(names) == 80
    outputs.check_targets(out, list(names))   # every file recognised as rescu's
    assert not (out / outputs.WORK).exists()


# ------------------------------------------------------------ config and image bombs
def _bomb() -> str:
    """Nine nested anchors under ``stage1.max_patterns``: 9**9 strings once expanded."""
    levels = ["&a [" + ",".join(['"lol"'] * 9) + "]"]
    for prev, name in zip("abcdefgh", "bcdefghi"):
        levels.append(f"&{name} [" + ",".join([f"*{prev}"] * 9) + "]")
    return "stage1:\n  max_patterns: [" + ", ".join(levels) + "]\n"


BOMB = _bomb()


WRAP = ("import resource, subprocess, sys, time\n"
        "t0 = time.monotonic()\n"
        "r = subprocess.run(sys.argv[1:])\n"
        "sys.stderr.write('PEAK %d %f\\n' % (resource.getrusage(resource.RUSAGE_CHILDREN)"
        ".ru_maxrss * 1024, time.monotonic() - t0))\n"
        "sys.exit(r.returncode)\n")


def _peak_and_time(cmd: list[str], **kw):
    """Run ``cmd``; its exit, output, the peak RSS (bytes) of its largest process and
    its seconds. Measured by a small wrapper process: a child's ``ru_maxrss`` starts
    at its parent's size when forked, and this test's process holds the suite's models."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", WRAP, *cmd], capture_output=True,
                          text=True, timeout=300, **kw)
    lines = proc.stderr.splitlines()
    peak, secs = lines[-1].split()[1:]
    proc.stderr = "\n".join(lines[:-1]) + ("\n" if len(lines) > 1 else "")
    return proc, int(peak), float(secs)


def test_a_yaml_alias_bomb_is_refused_at_once_with_a_short_message(photo, tmp_path):
    import sys

    cfg = tmp_path / "bomb.yaml"
    cfg.write_text(BOMB)
    proc, peak, secs = _peak_and_time(
        [sys.executable, "-m", "rescu.cli", "discover", str(photo), "--out",
         str(tmp_path / "out"), "--config", str(cfg)])
    assert_one_line_error(proc, "bomb.yaml", "stage1.max_patterns", "alias bomb")
    assert len(proc.stderr) < 400 and secs < 60 and peak < 1.5 * 2**30


def test_a_yaml_alias_bomb_is_refused_by_the_workflow(tmp_path):
    import subprocess
    import sys

    from test_cli import REPO

    cfg = tmp_path / "bomb.yaml"
    cfg.write_text(BOMB)
    proc, peak, secs = _peak_and_time(
        [str(Path(sys.executable).parent / "snakemake"), "-s", str(REPO / "Snakefile"),
         "--directory", str(tmp_path), "--configfile", str(cfg), "-n"])
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "alias bomb" in proc.stderr and len(proc.stderr) < 2000
    assert secs < 120 and peak < 1.5 * 2**30


def test_a_bomb_through_snakemakes_config_values_is_refused():
    from rescu.config import typed_cli_overrides

    bomb = ["x"] * 9
    for _ in range(9):
        bomb = [bomb] * 9
    with pytest.raises(InputError, match=r"--config: stage1\.max_patterns: more than"):
        typed_cli_overrides({"stage1": {"max_patterns": bomb}})


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_nan_and_inf_are_refused_wherever_a_number_is_read(tmp_path, value):
    from rescu.config import load_config

    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"stage1: {{sigma_s: {value}}}\n")
    with pytest.raises(InputError, match=r"c\.yaml: stage1\.sigma_s = .*not a finite number"):
        load_config(cfg, stage2=False)
    with pytest.raises(InputError, match=r"--set: dense\..* not a finite number"):
        load_config(overrides={"dense": {"min_confidence": float(value.replace(".", "")
                                                                   .replace("nan", "nan"))}},
                    stage2=False)


def test_a_16_bit_png_under_the_pixel_limit_decodes_within_the_memory_budget(tmp_path):
    import subprocess
    import sys

    import numpy as np
    from PIL import Image

    a = np.zeros((10000, 10000), np.uint16)
    a[::97, :] = 40000
    png = tmp_path / "big16.png"
    Image.fromarray(a).save(png)
    del a
    probe = ("import re, sys; from rescu.io import load_image; "   # VmHWM: this process's
             "r = load_image(sys.argv[1]); print(r.rgb.shape, r.rgb.dtype, r.rgb.max()); "
             "print(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())[1])")
    proc = subprocess.run([sys.executable, "-c", probe, str(png)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    shape, peak_kb = proc.stdout.splitlines()
    assert shape.startswith("(1600, 1600, 3) uint8 ") and int(shape.split()[-1]) > 0
    assert int(peak_kb) * 1024 < 1.5 * 2**30


def test_a_deep_image_over_the_byte_budget_is_refused_before_decoding(tmp_path):
    import numpy as np
    from PIL import Image

    from rescu.io import load_image

    png = tmp_path / "deep.tif"
    Image.fromarray(np.zeros((100, 100), np.int32), "I").save(png)
    with pytest.raises(InputError, match=r"deep\.tif: 100x100 I image decodes to"):
        load_image(png, max_pixels=12000)  # 40,000 bytes over 12,000 x 3


# ------------------------------------------------------------ malformed inputs, one line
def _coco(tmp_path: Path, d) -> Path:
    p = tmp_path / "annotations.json"
    p.write_text(json.dumps(d) if not isinstance(d, str) else d)
    return p


IMG = {"id": 1, "file_name": "images/a.jpg"}


@pytest.mark.parametrize("d, needle", [
    ([], "top level must be an object"),
    ("[" * 200_000 + "]" * 200_000, "nested too deeply"),
    ({"images": [{"id": [1], "file_name": "a.jpg"}], "annotations": []},
     "images[0].id must be a number or a string"),
    ({"images": [{"id": 1, "file_name": "x" * 1_000_000}], "annotations": []},
     "images[0].file_name must be a path of 1 to 4096"),
    ({"images": [IMG], "annotations": [{"image_id": [1], "category_id": 1,
                                        "bbox": [0, 0, 1, 1]}]}, "annotations[0].image_id"),
    ({"images": [IMG], "annotations": [{"image_id": 1, "category_id": {"a": 1},
                                        "bbox": [0, 0, 1, 1]}]}, "annotations[0].category_id"),
    ({"images": [IMG], "annotations": [{"image_id": 1, "category_id": 1,
                                        "bbox": [0, 0, -5, 1]}]}, "negative width"),
    ({"images": [IMG], "annotations": [{"image_id": 1, "category_id": 1,
                                        "bbox": [0, 0, float("inf"), 1]}]}, "not finite"),
])
def test_a_malformed_annotations_file_is_one_line_naming_the_field(tmp_path, d, needle):
    from rescu.io import load_coco_rps

    with pytest.raises(InputError) as e:
        load_coco_rps(_coco(tmp_path, d))
    assert "annotations.json" in str(e.value) and needle in str(e.value)
    assert len(str(e.value)) < 500


@pytest.mark.parametrize("im, needle", [
    ({"file_name": "a.jpg", "width": "abc", "height": 480, "vanishing_points": []},
     "images[0].width must be a number of pixels"),
    ({"file_name": "a.jpg", "width": 640, "height": 480, "vanishing_points": 3},
     "images[0].vanishing_points must be a list"),
    ({"file_name": "a.jpg", "width": 640, "height": 480,
      "vanishing_points": [{"homogeneous": [1, "x", 0]}]}, "three finite numbers"),
])
def test_a_malformed_vanishing_points_file_names_file_and_field(tmp_path, im, needle):
    from rescu.io import load_vanishing_points

    p = tmp_path / "vanishing_points.json"
    p.write_text(json.dumps({"images": [im]}))
    with pytest.raises(InputError, match="vanishing_points.json: ") as e:
        load_vanishing_points(p)
    assert needle in str(e.value)


@pytest.mark.parametrize("box, needle", [([0, 0, float("nan"), 3], "not finite"),
                                         ([0, 0, -4, 3], "negative width"),
                                         ([0, 0, 1e400, 3], "not finite")])
def test_a_prediction_with_a_bad_box_is_refused_not_scored(tmp_path, box, needle):
    from rescu.io import read_result

    p = tmp_path / "a.json"
    p.write_text(json.dumps({"image": "images/a.jpg", "width": 10, "height": 10,
                             "method": "rescu-ii", "dominant_pattern": 0,
                             "patterns": [{"id": 0, "score": 1.0, "count": 1,
                                           "instances": [{"bbox": box, "score": 1.0,
                                                          "source": "stage1"}]}]}))
    with pytest.raises(InputError, match=r"a\.json: patterns\[0\]\.instances\[0\]\.bbox"):
        read_result(p)
    with pytest.raises(InputError) as e:
        read_result(p)
    assert needle in str(e.value)


@pytest.mark.parametrize("where", ["/", "~", ""])
def test_results_dir_at_the_root_or_home_is_refused(where):
    from rescu.config import load_config

    with pytest.raises(InputError, match="results_dir"):
        load_config(overrides={"results_dir": where}, stage2=False)


def test_escape_codes_in_a_file_name_do_not_reach_the_terminal(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    photo = shelf_photo(folder / "evil\x1b[2J\x1b]0;pwned\x07.png")
    proc = _discover(photo, tmp_path / "out")
    assert proc.returncode == 0, proc.stderr
    assert "\x1b" not in proc.stdout + proc.stderr and "\x07" not in proc.stdout
    assert "evil\\x1b[2J" in proc.stdout


def test_a_second_run_appends_to_the_log_another_run_writes(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    first = outputs.open_log(out)
    first.write("first run\n")
    first.flush()
    second = outputs.open_log(out)              # the first still writes it: not emptied
    second.write("second run\n")
    second.flush()
    assert (out / "rescu.log").read_text() == "first run\nsecond run\n"
    outputs.close_log(out, first)
    outputs.close_log(out, second)
    third = outputs.open_log(out)               # nobody writes it: a fresh log
    outputs.close_log(out, third)
    assert (out / "rescu.log").read_text() == ""
    assert outputs.foreign_own(out) == []       # recorded as rescu's


def test_a_folder_written_by_an_earlier_rescu_still_runs(photo, tmp_path):
    """A manifest without "own" (rescu before it recorded its log and page): the log and
    page there are rescu's, replaced without --force."""
    out = tmp_path / "out"
    assert _discover(photo, out).returncode == 0
    m = json.loads((out / outputs.MANIFEST).read_text())
    del m["own"]
    (out / outputs.MANIFEST).write_text(json.dumps(m))
    (out / "index.html").write_text("<p>an earlier gallery</p>")
    assert _discover(photo, out).returncode == 0
    assert "shelf" in (out / "index.html").read_text()
    assert "own" in json.loads((out / outputs.MANIFEST).read_text())
