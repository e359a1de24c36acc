"""A photo's result set in the user's output folder (rescu.outputs): nothing rescu did not
write is replaced (API and CLI), a rerun replaces the whole set, a kill leaves no partial
set and no stray folder, and a write error fails one photo (a full disk stops the run)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rescu import cli, core, outputs
from rescu.api import discover
from rescu.config import load_config
from rescu.io import InputError
from test_cli import RESCU, shelf_photo


@pytest.fixture(scope="module")
def cfg():
    return load_config(stage2=False)


def run(photo, out, cfg, **kw):
    return discover(photo, out_dir=out, method="rescu-i", config=cfg, **kw)


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------- item 1: API
def test_api_never_replaces_a_sibling_photo(tmp_path, cfg):
    """discover('d/grid.jpg', out_dir='d') replaced the sibling photo d/grid.png with the
    overlay, silently."""
    d = tmp_path / "d"
    d.mkdir()
    shelf_photo(d / "grid.png")
    Image.open(d / "grid.png").convert("RGB").save(d / "grid.jpg", quality=95)
    before = files(d)
    with pytest.raises(outputs.OverwriteError, match=r"grid.png: not written by rescu"):
        run(d / "grid.jpg", d, cfg)
    assert files(d) == before


def test_api_refuses_names_that_leave_out_dir(tmp_path, cfg):
    photo = shelf_photo(tmp_path / "s.png")
    out = tmp_path / "a" / "b"
    for name in ("../../x", "sub/x", "..", "", ".rescu-results"):
        with pytest.raises(InputError, match="name"):
            run(photo, out, cfg, name=name)
    assert not (tmp_path / "x.json").exists() and not out.exists()


def test_api_type_error_names_the_argument():
    with pytest.raises(TypeError, match=r"image must be a path \(str or os.PathLike\), got int"):
        discover(123)


# ----------------------------------------------------------------------- item 2: CLI
def test_cli_refuses_files_it_did_not_write_and_force_replaces_them(tmp_path, capsys):
    """Any <stem>.png / <stem>.json in --out was replaced with exit 0; now exit 2 naming the
    file before any work; --force replaces; rescu's own results are replaced silently."""
    photo = shelf_photo(tmp_path / "x.png")
    out = tmp_path / "out"
    out.mkdir()
    (out / "x.json").write_text('{"my": "notes"}')
    args = ["discover", str(photo), "--out", str(out), "--method", "rescu-i", "--quiet"]
    assert cli.main(args) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert f"{out / 'x.json'}: not written by rescu" in err and "--force" in err
    assert (out / "x.json").read_text() == '{"my": "notes"}' and not (out / "x.png").exists()
    assert cli.main(args + ["--force"]) == cli.EXIT_OK
    assert json.loads((out / "x.json").read_text())["method"] == "rescu-i"
    assert cli.main(args) == cli.EXIT_OK  # its own results: a rerun replaces them
    (out / "x.png").write_bytes(b"someone's picture now")  # changed since: not rescu's
    assert cli.main(args) == cli.EXIT_USAGE
    assert "x.png: not written by rescu (or changed since)" in capsys.readouterr().err
    assert (out / "x.png").read_bytes() == b"someone's picture now"


# ----------------------------------------------------------------------- item 8: reruns
def test_rerun_replaces_the_whole_result_set(tmp_path, cfg, monkeypatch):
    """A rerun with fewer rectified views left the old rp2..rp9.png beside the new JSON."""
    photo = shelf_photo(tmp_path / "x.png")
    out = tmp_path / "out"
    real = core.analyse_scene

    def scene_with(n):
        def analyse_scene(prep, src, params):
            res, _ = real(prep, src, params)
            return res, {k: np.full((8, 8, 3), k, np.uint8) for k in range(n)}  # n views
        return analyse_scene

    for n, want in ((5, {f"rp{k}.png" for k in range(5)}), (1, {"rp0.png"}), (0, None)):
        monkeypatch.setattr(core, "analyse_scene", scene_with(n))
        run(photo, out, cfg)
        rect = out / "x_rectified"
        assert (sorted(p.name for p in rect.iterdir()) if rect.exists() else None) == \
            (sorted(want) if want else None)
    assert sorted(p.name for p in out.iterdir()) == [".rescu-lock", ".rescu-results.json", "x.json", "x.png"]
    manifest = json.loads((out / ".rescu-results.json").read_text())
    assert sorted(manifest["results"]["x"]["files"]) == ["x.json", "x.png"]


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killed_run_leaves_no_partial_set_nor_temporary_folder(tmp_path, cfg, sig):
    """A kill left x_rectified/ without a JSON and a temporary rescu-* folder per kill."""
    photo = shelf_photo(tmp_path / "x.png")
    out = tmp_path / "out"
    proc = subprocess.Popen([str(RESCU), "discover", str(photo), "--out", str(out), "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    work = out / outputs.WORK
    deadline = time.monotonic() + 120
    while not (work.is_dir() and any(work.iterdir())) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, "finished before it could be killed"
    time.sleep(0.5)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    assert not (out / "x.json").exists() and not (out / "x_rectified").exists()
    assert not list(Path(tempfile.gettempdir()).glob(f"rescu-{proc.pid}-*"))
    if sig == signal.SIGTERM:  # the cleanup ran
        assert not work.exists()
    run(photo, out, cfg)  # the next run removes a killed run's staging folder
    assert not work.exists() and (out / "x.json").is_file()


# ----------------------------------------------------------------------- item 4: writes
def _three_photos(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for s in "abc":
        shelf_photo(folder / f"{s}.png")
    return folder


def test_unwritable_result_is_a_per_photo_failure(tmp_path, monkeypatch, capsys):
    folder, out = _three_photos(tmp_path), tmp_path / "out"
    real = os.replace

    def replace(src, dst):
        if Path(dst) == out / "b.json":
            raise PermissionError(errno.EACCES, "Permission denied", str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    code = cli.main(["discover", str(folder), "--out", str(out), "--method", "rescu-i",
                     "--quiet"])
    captured = capsys.readouterr()
    assert code == cli.EXIT_IMAGE_FAILED, captured.err
    assert "b.png: FAILED in write: [Errno 13] Permission denied" in captured.out
    assert "2 of 3 image(s) done" in captured.out and "Traceback" not in captured.err
    assert (out / "a.json").is_file() and (out / "c.json").is_file()
    assert not (out / "b.json").exists()


def test_full_disk_stops_with_a_message_and_keeps_the_results_written(tmp_path, monkeypatch,
                                                                       capsys):
    folder, out = _three_photos(tmp_path), tmp_path / "out"
    real = os.replace
    written = {}

    def replace(src, dst):
        if Path(dst).name == "b.json" and Path(dst).parent != out:  # b's staged result
            written.update({k: v for k, v in files(out).items()
                            if not k.startswith(outputs.WORK)})  # a's results
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    code = cli.main(["discover", str(folder), "--out", str(out), "--method", "rescu-i",
                     "--quiet"])
    err = capsys.readouterr().err
    assert code == cli.EXIT_IMAGE_FAILED and "Traceback" not in err
    assert "No space left on device; stopped at" in err and "1 of 3 photo(s) done" in err
    now = files(out)
    results = outputs.MANIFEST  # the log's own record changes when it closes; the results not
    assert {k: v for k, v in now.items() if k != results} == \
        {k: v for k, v in written.items() if k != results}
    assert json.loads(now[results])["results"] == json.loads(written[results])["results"]
    assert "a.json" in written and "c.json" not in written
    assert not (out / outputs.WORK).exists()


# ----------------------------------------------------------------------- item 9: minor
def test_folder_mode_names_what_it_skips(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    shelf_photo(folder / "a.png")
    (folder / "b.jpg").symlink_to(tmp_path / "gone.jpg")
    assert cli._collect_photos([str(folder)]) == [folder / "a.png"]
    assert "skipped in" in (err := capsys.readouterr().err) and "b.jpg (broken symbolic link" in err
    with pytest.raises(InputError, match="b.jpg: broken symbolic link"):
        cli._collect_photos([str(folder / "b.jpg")])


def test_evaluate_says_how_many_predictions_are_missing(tmp_path, capsys):
    ds, preds = tmp_path / "ds", tmp_path / "preds"
    ds.mkdir(), preds.mkdir()
    (ds / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "a.png"}, {"id": 2, "file_name": "b.png"}],
        "annotations": [{"id": k, "image_id": i, "category_id": 1, "bbox": [10 * k, 0, 8, 8]}
                        for i in (1, 2) for k in (1, 2)],
        "categories": [{"id": 1, "name": "thing"}]}))
    (preds / "a.json").write_text(json.dumps({"image": "a.png", "width": 50, "height": 50,
                                              "method": "x", "patterns": []}))
    assert cli.evaluate_predictions_cli(ds, preds) == 0
    err = capsys.readouterr().err
    assert "1 of 2 image(s)" in err and "b.json" in err and "count as no detection" in err


# ----------------------------------------------------------------------- item 3: memory
def test_discover_on_a_20000_pixel_png_stays_small_and_goes_on(tmp_path):
    """A 0.4 MB 20000x20000 PNG took 5.6 GB; now it is refused from its header (a failure
    record) and the next photo is done, the whole command under 300 MB."""
    from test_io import _huge_png

    folder = tmp_path / "photos"
    folder.mkdir()
    _huge_png(folder / "a_huge.png", 20000)
    shelf_photo(folder / "b.png")
    out = tmp_path / "out"
    code = ("import resource, subprocess, sys; p = subprocess.run(sys.argv[1:]); "
            "print(p.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    proc = subprocess.run([sys.executable, "-c", code, str(RESCU), "discover",
                           str(folder / "a_huge.png"), "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    returncode, max_rss_kb = map(int, proc.stdout.split()[-2:])
    assert returncode == cli.EXIT_IMAGE_FAILED, proc.stdout
    assert "a_huge.png: FAILED in prepare" in proc.stdout and "image too large" in proc.stdout
    assert max_rss_kb < 300 * 1024, f"peak {max_rss_kb / 1024:.0f} MB"
    proc = subprocess.run([str(RESCU), "discover", str(folder), "--out", str(out), "--method",
                           "rescu-i", "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == cli.EXIT_IMAGE_FAILED and "Traceback" not in proc.stderr
    assert "1 of 2 image(s) done" in proc.stdout and (out / "b.json").is_file()
    assert json.loads((out / "a_huge.json").read_text())["failure"]["stage"] == "prepare"
