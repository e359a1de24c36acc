"""What a user must be able to trust: their photos are never touched, a wrong parameter
is named before any work starts, no input gives a traceback, and the installed package
works outside the checkout."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from PIL import Image

from test_cli import REPO, rescu, shelf_photo

SNAKEMAKE = Path(sys.executable).parent / "snakemake"


def checksums(folder: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of every file under ``folder``."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("rescu: error: "), proc.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])


@pytest.fixture
def photos(tmp_path: Path) -> Path:
    """A folder with ``x.png`` and ``x.jpg`` (one stem) and the user's own ``x.json``."""
    folder = tmp_path / "photos"
    folder.mkdir()
    shelf_photo(folder / "x.png")
    Image.open(folder / "x.png").convert("RGB").save(folder / "x.jpg", quality=95)
    (folder / "x.json").write_text('{"my": "notes"}')
    return folder


# ----------------------------------------------------------------------- user's files
def test_out_holding_the_photos_is_refused_and_nothing_is_touched(photos):
    before = checksums(photos)
    for out in (photos, photos.parent):  # the photos' folder, or one that contains it
        proc = rescu("discover", str(photos), "--out", str(out), "--method", "rescu-i")
        assert_one_line_error(proc, "--out", "holds the input photo")
        assert checksums(photos) == before


def test_photos_sharing_a_stem_get_distinct_results(photos, tmp_path):
    out = tmp_path / "out"
    proc = rescu("discover", str(photos), "--out", str(out), "--method", "rescu-i", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "2 of 2 image(s) done" in proc.stdout
    a = json.loads((out / "x.jpg.json").read_text())
    b = json.loads((out / "x.png.json").read_text())
    assert a["image"] == "x.jpg" and b["image"] == "x.png"
    assert (out / "x.jpg.png").is_file() and (out / "x.png.png").is_file()
    assert not (out / "x.json").exists()


def test_two_folders_with_one_file_name_are_refused_before_work(tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        shelf_photo(tmp_path / d / "x.png")
    out = tmp_path / "out"
    proc = rescu("discover", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out))
    assert_one_line_error(proc, "x.png", "same result files")
    assert not out.exists()


# ----------------------------------------------------------------------- parameters
@pytest.mark.parametrize("setting, needles", [
    ("stage1.max_patterns=-1", ["--set", "stage1.max_patterns", "-1", "minimum of 1"]),
    ("stage1.max_patterns=abc", ["--set", "stage1.max_patterns", "'abc'", "integer"]),
    ("stage1.nonexistent=1", ["--set", "unknown key 'stage1.nonexistent'", "max_patterns"]),
    ("stage1.max_pattern=3", ["did you mean 'max_patterns'"]),
    ("grasp.max_patterns=0", ["--set", "grasp.max_patterns"]),
    ("scene.vp.min_lines=1", ["--set", "scene.vp.min_lines"]),
    ("stage2.backbone.name=densenet121", ["stage2.backbone.name", "weights not found"]),
    ("stage2.backbone.nam=x", ["unknown key 'stage2.backbone.nam'", "did you mean 'name'"]),
    ("stage2.visible_half=true", ["unknown key 'stage2.visible_half'"]),
    ("stage1.max_patterns=[1", ["--set", "stage1.max_patterns=[1", "not valid YAML"]),
    ("stage1", ["--set expects KEY=VALUE"]),
    ("stage2.backbone.device=potato", ["--set", "stage2.backbone.device = 'potato'",
                                       "does not match"]),
    ("stage1.min_instances=300", ["--set", "stage1.min_instances = 300 is more than "
                                  "stage1.max_cols = 200"]),
])
def test_bad_parameter_is_named_before_any_image(photos, tmp_path, setting, needles):
    out = tmp_path / "out"
    proc = rescu("discover", str(photos / "x.png"), "--out", str(out), "--set", setting)
    assert_one_line_error(proc, *needles)
    assert not out.exists()  # nothing started


def test_bad_key_in_config_file_names_the_file(photos, tmp_path):
    cfg = tmp_path / "mine.yaml"
    cfg.write_text("stage1:\n  max_patterns: 3\n  min_words: 1\n")
    proc = rescu("discover", str(photos / "x.png"), "--out", str(tmp_path / "o"),
                 "--config", str(cfg))
    assert_one_line_error(proc, str(cfg), "stage1.min_words = 1")
    cfg.write_text("stage1: [1\n")
    assert_one_line_error(rescu("discover", str(photos / "x.png"), "--out", str(tmp_path / "o"),
                                "--config", str(cfg)), str(cfg), "malformed YAML")


def test_edge_model_file_is_checked_before_any_image(photos, tmp_path):
    """EdgeBoxes with a missing structured-edge model: every photo ran stage I, then raw
    OpenCV messages and exit 1."""
    out = tmp_path / "out"
    proc = rescu("discover", str(photos / "x.png"), "--out", str(out),
                 "--set", "stage2.proposals.method=edgeboxes",
                 "--set", "stage2.proposals.edge_model_path=/missing/model.yml.gz")
    assert_one_line_error(proc, "--set", "stage2.proposals.edge_model_path = "
                          "'/missing/model.yml.gz': file not found")
    assert not out.exists()


def test_cuda_without_a_gpu_is_refused_before_any_image(monkeypatch):
    import torch

    from rescu.config import load_config
    from rescu.io import InputError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for device in ("cuda", "cuda:1"):
        with pytest.raises(InputError, match=f"--set: stage2.backbone.device = "
                                             f"'{device}': no CUDA GPU on this machine"):
            load_config(overrides={"stage2": {"backbone": {"device": device}}})
    load_config(overrides={"stage2": {"backbone": {"device": "cuda"}}}, stage2=False)


def test_densenet_weights_not_needed_for_stage_one(photos, tmp_path):
    proc = rescu("discover", str(photos / "x.png"), "--out", str(tmp_path / "o"), "--quiet",
                 "--method", "rescu-i", "--set", "stage2.backbone.name=densenet121")
    assert proc.returncode == 0, proc.stderr


def test_validate_config_checks_every_section():
    from rescu.config import load_config, validate_config
    from rescu.io import InputError

    cfg = load_config()
    assert validate_config(cfg) is cfg
    bad = [({"stage2_ablation": {"predict_variants": {"v": {"head": {"lr": 0.1}}}}},
            "not the predict section"),
           ({"ablation": {"variants": {"v": ["P_q"]}}}, "ablation.variants.v.0"),
           ({"caption": {"captioner": "gpt"}}, "caption.captioner"),
           ({"features": {"n_features": 0}}, "features.n_features"),
           ({"synthetic": {"min_rps": 0}}, "synthetic.min_rps"),
           ({"evaluation": {"iod_h": 1.5}}, "evaluation.iod_h"),
           ({"dense": {"mode": "sparse"}}, "dense.mode"),
           ({"dense": {"surround": 4}}, "dense.surround"),
           ({"dense": {"max_touching": 5}}, "dense.max_touching"),
           ({"ablation": {"variants": {"dense-only": ["P_d"]}}},
            "ablation.variants.dense-only: the name of a source row")]
    for over, needle in bad:
        with pytest.raises(InputError, match=needle.replace(".", r"\.")):
            load_config(overrides=over)


@pytest.mark.slow
def test_snakefile_checks_the_config_before_any_job(tmp_path):
    for setting, needle in (("stage1={max_patterns: -1}", "stage1.max_patterns = -1"),
                            ("stage1={nonexistent: 1}", "unknown key 'stage1.nonexistent'")):
        proc = subprocess.run([str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--directory",
                               str(tmp_path), "-n", "--cores", "1", "--config", setting],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert f"rescu: error: --config: {needle}" in proc.stderr
        assert "Traceback" not in proc.stderr


def test_defaults_exist_once_inside_the_package():
    """The default configuration, its schema and the objects profile have one copy, in
    rescu/defaults/; config/config.yaml holds overrides only (none shipped), and the
    Snakefile reads the package's defaults and validates with rescu.config alone."""
    import yaml

    shipped = {p.name: p.read_bytes() for p in (REPO / "rescu" / "defaults").glob("*.yaml")}
    assert set(shipped) == {"config.yaml", "config.schema.yaml", "objects.yaml"}
    assert yaml.safe_load((REPO / "config" / "config.yaml").read_text()) == {}
    for other in [*(REPO / "config").glob("*.yaml"), *(REPO / "profiles").rglob("*.yaml")]:
        assert other.name not in {"config.schema.yaml", "objects.yaml"}, other
        assert other.read_bytes() not in shipped.values(), other
    snakefile = (REPO / "Snakefile").read_text()
    assert "configfile: str(DEFAULT_CONFIG)" in snakefile
    assert "validate(" not in snakefile.replace("validate_config(", "")


# ----------------------------------------------------------------------- no traceback
def test_out_that_is_a_file_or_cannot_be_created(photos, tmp_path):
    f = tmp_path / "afile"
    f.write_text("keep me")
    assert_one_line_error(rescu("discover", str(photos / "x.png"), "--out", str(f)),
                          "--out", "not a folder")
    assert_one_line_error(rescu("discover", str(photos / "x.png"), "--out", str(f / "sub")),
                          "--out", "cannot be created")
    assert f.read_text() == "keep me"
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o555)
        assert_one_line_error(rescu("discover", str(photos / "x.png"), "--out", str(ro)),
                              "--out", "not writable")


def test_evaluate_empty_or_bad_predictions(tmp_path):
    from rescu.data.synth import SynthParams, generate_dataset

    ds = tmp_path / "ds"
    generate_dataset(ds, SynthParams.from_dict({"n_images": 1, "sizes": [[480, 360]]}))
    preds = tmp_path / "preds"
    preds.mkdir()
    assert_one_line_error(rescu("evaluate", str(ds), str(preds)), "no prediction files")
    (preds / "other.json").write_text("{}")
    assert_one_line_error(rescu("evaluate", str(ds), str(preds)), "none of its 1 JSON")
    stem = Path(json.loads((ds / "annotations.json").read_text())["images"][0]["file_name"]).stem
    for box in ([1, 2, -3, 4], [1, 2, "NaN", 4], [1, 2, 3]):
        (preds / f"{stem}.json").write_text(json.dumps(
            {"image": "x", "width": 480, "height": 360, "method": "m",
             "patterns": [{"id": 0, "score": 1, "count": 1, "instances": [{"bbox": box}]}]}
        ).replace('"NaN"', "NaN"))
        assert_one_line_error(rescu("evaluate", str(ds), str(preds)), f"{stem}.json", "bbox")


def test_api_raises_clear_exceptions(tmp_path, capfd):
    from rescu import discover
    from rescu.io import InputError

    with pytest.raises(FileNotFoundError, match="missing.jpg: file not found"):
        discover(tmp_path / "missing.jpg")
    photo = shelf_photo(tmp_path / "s.png")
    with pytest.raises(InputError, match="stage1.max_patterns"):
        from rescu.config import load_config

        cfg = load_config()
        cfg["stage1"]["max_patterns"] = "abc"
        discover(photo, config=cfg, method="rescu-i")
    with pytest.raises(InputError, match="would overwrite"):
        discover(photo, out_dir=tmp_path, method="rescu-i")
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"garbage")
    res = discover(bad, method="rescu-i")  # a bad image is a documented empty result
    assert res.extra["failure"]["stage"] == "prepare" and not res.patterns
    assert capfd.readouterr().err == ""


# ----------------------------------------------------------------------- installed
@pytest.mark.slow
def test_wheel_installed_outside_the_checkout_runs(tmp_path):
    """``pip wheel .``, installed into a new virtual environment in a folder outside the
    checkout; the heavy dependencies (torch, OpenCV, ...) come from this environment's
    site-packages through a ``.pth`` file (a second 5 GB install is not what is tested)."""
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "--no-build-isolation", "-w", str(wheels), str(REPO)], check=True,
                   capture_output=True, timeout=600)
    (wheel,) = wheels.glob("rescu-*.whl")
    # the new environment sees no checkout: with PYTHONPATH on one, pip would take rescu
    # as installed already and skip the wheel
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=600)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_path("
                                "'purelib'))"], capture_output=True, text=True, env=env,
                               check=True).stdout.strip())
    (site / "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
                    str(wheel)], check=True, capture_output=True, timeout=600, env=env)
    work = tmp_path / "elsewhere"
    work.mkdir()
    shelf_photo(work / "shelf.png")
    where = subprocess.run([str(py), "-c", "import rescu; print(rescu.__file__)"], cwd=work,
                           capture_output=True, text=True, env=env, check=True).stdout
    assert where.startswith(str(site)), where  # the installed copy, not the checkout
    exe = venv / "bin" / "rescu"
    version = subprocess.run([str(exe), "--version"], cwd=work, capture_output=True,
                             text=True, env=env)
    assert version.returncode == 0 and version.stdout.strip() == "rescu 0.1.0"
    proc = subprocess.run([str(exe), "discover", "shelf.png", "--out", "out", "--quiet"],
                          cwd=work, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    d = json.loads((work / "out" / "shelf.json").read_text())
    assert d["method"] == "rescu-ii" and max(p["count"] for p in d["patterns"]) >= 5
    shutil.rmtree(venv)


def test_summary_line_of_a_degraded_result_shows_patterns_and_the_failure():
    from rescu.cli import _summary_line
    from rescu.types import ImageResult, Instance, Pattern

    res = ImageResult(image="x.jpg", width=10, height=10, method="rescu-ii",
                      patterns=[Pattern(0, 1.0, [Instance((0, 0, 2, 2)), Instance((4, 0, 2, 2))])],
                      extra={"failure": {"stage": "stage2-predict", "message": "boom",
                                         "type": "ValueError", "degraded_to": "rescu-i"}})
    line = _summary_line("x.jpg", res)
    assert line.startswith("x.jpg: 1 RP: 2 (score 1.00)")
    assert "FAILED in stage2-predict: boom; rescu-i's result kept" in line
    res.extra["failure"].pop("degraded_to")
    assert _summary_line("x.jpg", res) == "x.jpg: FAILED in stage2-predict: boom"


def test_degraded_result_is_drawn_with_its_patterns(monkeypatch):
    import numpy as np

    from rescu import visualize
    from rescu.types import ImageResult, Instance, Pattern

    texts = []
    monkeypatch.setattr(visualize, "_wrap", lambda t, w: texts.append(t) or [t])
    res = ImageResult(image="x.jpg", width=60, height=40, method="rescu-ii",
                      patterns=[Pattern(0, 1.0, [Instance((2, 2, 8, 8)), Instance((20, 2, 8, 8))])],
                      caption={"base": "b", "enhanced": "Two similar objects."},
                      extra={"failure": {"stage": "stage2-train", "message": "boom",
                                         "degraded_to": "rescu-i"}})
    img = visualize.overlay(np.zeros((40, 60, 3), np.uint8), 1.0, res)
    assert img.shape[0] > 40
    assert texts == ["RP0: 2 instances, score 1.00",  # the legend, then the caption
                     "Two similar objects. [stage2-train failed; rescu-i's result shown]"]


def test_overlay_marks_the_images_vps():
    import numpy as np

    from rescu import visualize
    from rescu.types import ImageResult

    vps = [{"homogeneous": [30.0, 20.0, 1.0]},          # inside: a ring at (60, 40) (x2)
           {"homogeneous": [1.0, 0.0, 0.0]},            # at infinity: an arrow
           {"homogeneous": "bad"}]                      # malformed: skipped
    res = ImageResult(image="x.jpg", width=100, height=60, method="rescu-ii", patterns=[],
                      extra={"vanishing_points": vps})
    rgb = np.zeros((120, 200, 3), np.uint8)
    img = visualize.overlay(rgb, 2.0, res)[:120]
    white = (img == 255).all(axis=2)
    ys, xs = np.nonzero(white)
    ring = np.hypot(xs - 60, ys - 40)
    assert ((ring > 5) & (ring < 25)).any() and not white[40, 60]   # a ring, hollow
    # the arrow runs right from the centre (100, 60), 0.25 x the shorter side long
    assert white[60, 102:130].all() and not white[60, 185:].any()  # the label at its tip
    plain = visualize.overlay(rgb, 2.0, ImageResult("x.jpg", 100, 60, "rescu-ii", []))[:120]
    assert not (plain == 255).all(axis=2).any()
