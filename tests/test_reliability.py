"""Failure isolation, resumable runs and reproducible results (the pipeline as users run it).

These runs use stage I only (``scene.source: rescu-i``, targets up to the final JSON and
the failures table) to stay fast; stage II is covered by tests/test_workflow.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from rescu import pipeline
from rescu.io import read_json

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
TARGETS = ["results/tables/failures.tsv", "results/tables/captions.tsv"]


def _textured(seed: int, n: int = 5, size=(360, 480)) -> np.ndarray:
    """A row of ``n`` copies of one random texture on a smooth background."""
    rng = np.random.default_rng(seed)
    h, w = size
    img = np.full((h, w, 3), 90, np.uint8) + rng.integers(0, 20, (h, w, 3), dtype=np.uint8)
    tex = rng.integers(0, 255, (12, 12, 3), dtype=np.uint8).repeat(5, 0).repeat(5, 1)
    for k in range(n):
        x = 20 + k * 88
        img[150:210, x:x + 60] = tex
    return img


def make_photo_folder(root: Path) -> Path:
    """images/: two good photos, a truncated JPEG, a zero-byte file, text named .jpg."""
    imgs = root / "images"
    imgs.mkdir(parents=True)
    Image.fromarray(_textured(0)).save(imgs / "good_a.png")
    Image.fromarray(_textured(1)).save(imgs / "good_b.jpg", quality=95)
    Image.fromarray(_textured(2)).save(imgs / "cut.jpg", quality=95)
    (imgs / "cut.jpg").write_bytes((imgs / "cut.jpg").read_bytes()[:500])
    (imgs / "empty.jpg").write_bytes(b"")
    (imgs / "notes.jpg").write_text("not an image")
    return root


def config_for(tmp: Path, folder: Path) -> Path:
    default = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())
    datasets = {name: {"enabled": False} for name in default["datasets"]}
    datasets["mine"] = {"path": str(folder)}
    cfg = {"datasets": datasets, "scene": {"source": "rescu-i"}, "ablation": {"datasets": []}}
    p = tmp / "config.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def run(workdir: Path, cfg: Path, *args: str, cores: int = 2, check: bool = True):
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(cfg), "--cores", str(cores), *args, *TARGETS]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
    return proc


def result_files(workdir: Path) -> dict[str, bytes]:
    res = workdir / "results"
    files = sorted(res.glob("mine/final/*.json")) + sorted(res.glob("mine/rescu-i/*.json")) + \
        [res / "tables" / "failures.tsv", res / "tables" / "captions.tsv"]
    return {str(f.relative_to(res)): f.read_bytes() for f in files}


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("rel")
    folder = make_photo_folder(base / "photos")
    cfg = config_for(base, folder)
    work = base / "run_a"
    run(work, cfg, cores=2)
    return base, folder, cfg, work


def test_bad_images_do_not_stop_the_others(reference_run):
    _, _, _, work = reference_run
    finals = work / "results" / "mine" / "final"
    for name in ("good_a", "good_b"):
        d = read_json(finals / f"{name}.json")
        assert "failure" not in d and d["caption"]["enhanced"]
    for name, message in (("cut", "truncated"), ("empty", "empty file"),
                          ("notes", "not an image")):
        d = read_json(finals / f"{name}.json")
        assert d["patterns"] == [] and d["failure"]["stage"] == "prepare"
        assert message in d["failure"]["message"] and f"{name}.jpg" in d["failure"]["message"]
    failures = (work / "results" / "tables" / "failures.tsv").read_text()
    assert failures.count("prepare") == 3 and "good_a" not in failures


def test_same_input_same_bytes_across_runs_and_cores(reference_run):
    base, _, cfg, work = reference_run
    other = base / "run_b"
    run(other, cfg, cores=1)
    a, b = result_files(work), result_files(other)
    assert a.keys() == b.keys() and len(a) >= 12
    different = [k for k in a if a[k] != b[k]]
    assert not different, f"outputs differ between runs: {different}"


def test_killed_run_resumes_to_the_same_result(reference_run):
    base, _, cfg, work = reference_run
    resumed = base / "run_c"
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--directory", str(resumed),
           "--configfile", str(cfg), "--cores", "2", *TARGETS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.time() + 300
    feats = resumed / "results" / "mine" / "features"
    while time.time() < deadline and len(list(feats.glob("*.h5"))) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole run, jobs included, mid-way
    proc.wait()
    assert not (resumed / "results" / "tables" / "captions.tsv").exists(), "killed too late"
    # A truncated output never appears under its final name (writes are atomic).
    for f in (resumed / "results").rglob("*.json"):
        if not f.name.startswith("."):
            json.loads(f.read_text())
    run(resumed, cfg, "--unlock")  # Snakemake's lock survives a SIGKILL (README: resuming)
    run(resumed, cfg, "--rerun-incomplete")
    a, c = result_files(work), result_files(resumed)
    assert a == c


def test_step_functions_pass_failures_on(tmp_path):
    """Without Snakemake: a bad image yields empty outputs with the failure at each step."""
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG broken")
    w = lambda n: str(tmp_path / n)  # noqa: E731
    f = pipeline.prepare(str(bad), w("p.png"), w("m.json"), image_name="images/bad.png",
                         max_side=800, min_side=16)
    assert f and f["stage"] == "prepare"
    from rescu.config import load_config

    cfg = load_config()
    assert pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"])["stage"] == "prepare"
    assert pipeline.stage1(w("f.h5"), w("m.json"), w("s.json"), w("s.h5"),
                           cfg["stage1"])["stage"] == "prepare"
    scene = cfg["scene"]
    pipeline.scene(w("p.png"), w("m.json"), w("s.json"), w("sc.json"), w("rect"), scene)
    pipeline.caption(w("p.png"), w("m.json"), w("sc.json"), w("final.json"), cfg["caption"])
    d = json.loads(Path(w("final.json")).read_text())
    assert d["failure"]["stage"] == "prepare" and d["patterns"] == []


@pytest.mark.parametrize("kind", ["uniform", "single_object"])
def test_no_recurrence_gives_empty_patterns_not_failure(tmp_path, kind):
    """A uniform image (no features) or one object alone: empty patterns, no failure."""
    img = np.full((240, 320, 3), 128, np.uint8)
    if kind == "single_object":
        rng = np.random.default_rng(3)
        img[80:160, 120:200] = rng.integers(0, 255, (80, 80, 3), dtype=np.uint8)
    src = tmp_path / f"{kind}.png"
    Image.fromarray(img).save(src)
    w = lambda n: str(tmp_path / n)  # noqa: E731
    from rescu.config import load_config

    cfg = load_config()
    assert pipeline.prepare(str(src), w("p.png"), w("m.json"), image_name=src.name,
                            max_side=800, min_side=16) is None
    assert pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"]) is None
    assert pipeline.stage1(w("f.h5"), w("m.json"), w("s.json"), w("s.h5"), cfg["stage1"]) is None
    scene = cfg["scene"]
    assert pipeline.scene(w("p.png"), w("m.json"), w("s.json"), w("sc.json"), w("r"), scene) is None
    assert pipeline.caption(w("p.png"), w("m.json"), w("sc.json"), w("final.json"),
                            cfg["caption"]) is None
    d = json.loads(Path(w("final.json")).read_text())
    assert d["patterns"] == [] and d["vanishing_point"] is None and "failure" not in d
    assert d["caption"]["base"]


# ------------------------------------------------------------------ degradation (stage II)
def _boom(*_a, **_k):
    raise RuntimeError("injected failure")


def _through_stage1(tmp_path, cfg, img=None):
    """prepare, features, stage I on a textured image; returns the path helper."""
    src = tmp_path / "row.png"
    Image.fromarray(_textured(0) if img is None else img).save(src)
    w = lambda n: str(tmp_path / n)  # noqa: E731
    assert pipeline.prepare(str(src), w("p.png"), w("m.json"), image_name=src.name,
                            max_side=800, min_side=16) is None
    assert pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"]) is None
    assert pipeline.stage1(w("f.h5"), w("m.json"), w("s.json"), w("s.h5"), cfg["stage1"]) is None
    return w


def _stage2(w, cfg):
    p = cfg["stage2"]
    pipeline.stage2_features(w("p.png"), w("m.json"), w("s.json"), w("s2.h5"), p)
    pipeline.stage2_train(w("s2.h5"), w("s.json"), w("head.h5"), p)
    return pipeline.stage2_predict(w("s2.h5"), w("head.h5"), w("s.json"), w("ii.json"),
                                   w("m.json"), p)


@pytest.mark.parametrize("step, module, fn",
                         [("stage2-features", "proposal_features", "compute_stage2_features"),
                          ("stage2-train", "train", "train_heads"),
                          ("stage2-predict", "predict", "predict_stage2")])
def test_stage2_failure_keeps_stage1_patterns(tmp_path, monkeypatch, step, module, fn):
    """A stage-II exception: the RESCU-II JSON is stage I's result (method rescu-ii) with a
    degraded failure record, and scene and caption still run on it."""
    import importlib

    from rescu.config import load_config

    cfg = load_config()
    w = _through_stage1(tmp_path, cfg)
    monkeypatch.setattr(importlib.import_module(f"rescu.extension.{module}"), fn, _boom)
    f = _stage2(w, cfg)
    assert f == {"stage": step, "type": "RuntimeError", "message": "injected failure"}
    s1, ii = read_json(w("s.json")), read_json(w("ii.json"))
    assert s1["patterns"] and ii["patterns"] == s1["patterns"]
    assert ii["method"] == "rescu-ii"
    assert ii["failure"] == {**f, "degraded_to": "rescu-i"}
    assert pipeline.is_degraded(ii["failure"])
    assert {k: v for k, v in ii.items() if k not in ("method", "failure")} == \
        {k: v for k, v in s1.items() if k != "method"}
    assert pipeline.scene(w("p.png"), w("m.json"), w("ii.json"), w("sc.json"), w("rect"),
                          cfg["scene"]) is None
    assert pipeline.caption(w("p.png"), w("m.json"), w("sc.json"), w("final.json"),
                            cfg["caption"]) is None
    final = read_json(w("final.json"))
    assert final["method"] == "rescu-ii" and final["failure"] == ii["failure"]
    assert len(final["patterns"]) == len(s1["patterns"]) and final["caption"]["enhanced"]
    # the failures table still counts the image, with the patterns it kept
    from rescu.evaluation.tables import result_rows

    caps, fails = result_rows({"mine": [w("final.json")]})
    assert list(fails["stage"]) == [step] and int(caps["n_patterns"][0]) == len(s1["patterns"])


def test_stage2_variants_and_ablation_degrade_too(tmp_path, monkeypatch):
    from rescu.extension import proposal_features as features
    from rescu.config import load_config

    cfg = load_config()
    w = _through_stage1(tmp_path, cfg)
    s1 = read_json(w("s.json"))
    monkeypatch.setattr(features, "compute_stage2_features", _boom)
    _stage2(w, cfg)
    outs = {"vh": w("vh.json")}
    f = pipeline.stage2_predict_variants(w("s2.h5"), w("head.h5"), w("s.json"), w("m.json"),
                                         outs, cfg["stage2"],
                                         {"vh": {"predict": {"visible_half": True}}})
    assert f["stage"] == "stage2-features"
    d = read_json(outs["vh"])
    assert d["method"] == "rescu-ii[vh]" and d["patterns"] == s1["patterns"]
    assert d["failure"] == {**f, "degraded_to": "rescu-i"}
    outs = {"eb": w("eb.json"), "is": w("is.json")}
    f = pipeline.stage2_ablation(w("p.png"), w("m.json"), w("s.json"), outs, cfg["stage2"],
                                 {"eb": {"proposals": {"method": "edgeboxes"}},
                                  "is": {"proposals": {"method": "instance_scale"}}})
    assert f["stage"] == "stage2-ablation"
    for name, path in outs.items():
        d = read_json(path)
        assert d["method"] == f"rescu-ii[{name}]" and d["patterns"] == s1["patterns"]
        assert d["failure"] == {**f, "degraded_to": "rescu-i"}


def test_scene_failure_keeps_its_input_and_the_first_record(tmp_path, monkeypatch):
    """scene fails on a result that stage II already degraded: the scene JSON keeps the
    input's patterns; the record names scene, keeps degraded_to rescu-i and the stage-II
    record under "upstream"; caption runs."""
    from rescu.scene import analyse as SC
    from rescu.extension import predict
    from rescu.config import load_config

    cfg = load_config()
    w = _through_stage1(tmp_path, cfg)
    monkeypatch.setattr(predict, "predict_stage2", _boom)
    f2 = _stage2(w, cfg)
    monkeypatch.setattr(SC, "analyse_scene", _boom)
    f = pipeline.scene(w("p.png"), w("m.json"), w("ii.json"), w("sc.json"), w("rect"),
                       cfg["scene"])
    assert f["stage"] == "scene"
    ii, sc = read_json(w("ii.json")), read_json(w("sc.json"))
    assert sc["patterns"] == ii["patterns"] and sc["method"] == "rescu-ii"
    assert sc["failure"] == {**f, "degraded_to": "rescu-i",
                             "upstream": {**f2, "degraded_to": "rescu-i"}}
    assert pipeline.caption(w("p.png"), w("m.json"), w("sc.json"), w("final.json"),
                            cfg["caption"]) is None
    final = read_json(w("final.json"))
    assert final["failure"] == sc["failure"] and final["caption"]["enhanced"]


def test_upstream_failure_stays_empty_through_stage2(tmp_path):
    """A bad image: stage I has nothing to keep, so RESCU-II is empty with the prepare
    record (not degraded), and scene and caption skip as before."""
    from rescu.config import load_config

    cfg = load_config()
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG broken")
    w = lambda n: str(tmp_path / n)  # noqa: E731
    pipeline.prepare(str(bad), w("p.png"), w("m.json"), image_name="bad.png",
                     max_side=800, min_side=16)
    pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"])
    pipeline.stage1(w("f.h5"), w("m.json"), w("s.json"), w("s.h5"), cfg["stage1"])
    assert _stage2(w, cfg)["stage"] == "prepare"
    ii = read_json(w("ii.json"))
    assert ii["patterns"] == [] and ii["failure"]["stage"] == "prepare"
    assert not pipeline.is_degraded(ii["failure"])
    assert pipeline.scene(w("p.png"), w("m.json"), w("ii.json"), w("sc.json"), w("rect"),
                          cfg["scene"])["stage"] == "prepare"
    pipeline.caption(w("p.png"), w("m.json"), w("sc.json"), w("final.json"), cfg["caption"])
    final = read_json(w("final.json"))
    assert final["patterns"] == [] and "degraded_to" not in final["failure"]
    assert "caption" not in final or not final["caption"]


def test_image_vp_step_passes_failures_on_and_degrades(tmp_path, monkeypatch):
    """The joint VP step: a bad image stays empty with the prepare record; on a good one its
    own failure keeps the scene result (degraded), and without failure it adds the image's
    VPs; the peer step records a missing package as its failure."""
    from rescu.config import load_config
    from rescu.scene import image_vp as IV
    from rescu.scene.vp import peers

    cfg = load_config()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "bad.png").write_bytes(b"\x89PNG broken")
    b = lambda n: str(bad / n)  # noqa: E731
    pipeline.prepare(b("bad.png"), b("p.png"), b("m.json"), image_name="bad.png",
                     max_side=800, min_side=16)
    pipeline.features(b("p.png"), b("m.json"), b("f.h5"), cfg["features"])
    pipeline.stage1(b("f.h5"), b("m.json"), b("s.json"), b("s.h5"), cfg["stage1"])
    pipeline.scene(b("p.png"), b("m.json"), b("s.json"), b("sc.json"), b("r"), cfg["scene"])
    assert pipeline.image_vp(b("p.png"), b("m.json"), b("sc.json"), b("j.json"),
                             cfg["scene"])["stage"] == "prepare"
    assert read_json(b("j.json"))["patterns"] == []
    assert pipeline.peer_vp(b("p.png"), b("m.json"), b("lu.json"),
                            cfg["scene"]["peer_vp"])["stage"] == "prepare"

    w = _through_stage1(tmp_path, cfg)
    assert pipeline.scene(w("p.png"), w("m.json"), w("s.json"), w("sc.json"), w("r"),
                          cfg["scene"]) is None
    assert pipeline.image_vp(w("p.png"), w("m.json"), w("sc.json"), w("j.json"),
                             cfg["scene"], focal_px=500.0) is None
    sc, j = read_json(w("sc.json")), read_json(w("j.json"))
    assert j["patterns"] == sc["patterns"] and j["rp_vanishing_point"] == sc["vanishing_point"]
    assert isinstance(j["vanishing_points"], list) and "focal_px" in j
    monkeypatch.setattr(IV, "manhattan_vps", _boom)
    f = pipeline.image_vp(w("p.png"), w("m.json"), w("sc.json"), w("j2.json"), cfg["scene"])
    j2 = read_json(w("j2.json"))
    assert f["stage"] == "image-vp" and j2["failure"]["degraded_to"] == "rescu-i"
    assert j2["patterns"] == sc["patterns"] and j2["vanishing_point"] == sc["vanishing_point"]

    def absent(*_a, **_k):
        raise ImportError(peers.LU_INSTALL)

    monkeypatch.setattr(peers, "lu_vanishing_points", absent)
    f = pipeline.peer_vp(w("p.png"), w("m.json"), w("lu.json"), cfg["scene"]["peer_vp"])
    assert f["stage"] == "peer-vp" and "pip install --no-deps lu-vp-detect" in f["message"]
    assert read_json(w("lu.json"))["vanishing_point"] is None
