"""rescu.core: the stages in memory give what the file pipeline gives, with its failure
semantics, and rescu.discover writes nothing it was not asked for."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import rescu
from rescu import core, io, pipeline
from rescu.config import load_config
from rescu.io import InputError
from test_cli import shelf_photo


def _file_chain(photo: Path, work: Path, cfg: dict, method: str) -> dict:
    """The pipeline's per-image steps, file to file, as the Snakemake rules run them (with
    the thread counts their adapters set: torch's float sums depend on them)."""
    w = lambda n: str(work / n)  # noqa: E731
    backbone, head = cfg["threads"]["stage2_features"], cfg["threads"]["stage2_head"]
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    try:
        return _steps(photo, work, cfg, method, w, backbone, head)
    finally:
        torch.set_num_threads(before)


def _steps(photo: Path, work: Path, cfg: dict, method: str, w, backbone: int,
           head: int) -> dict:
    pipeline.prepare(str(photo), w("p.png"), w("m.json"), image_name=photo.name,
                     **{k: cfg["image"][k] for k in ("max_side", "min_side", "max_pixels")})
    pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"])
    dense = None
    if cfg["dense"]["enabled"]:
        dense = w("d.json")
        pipeline.limit_threads(backbone, torch=True)
        pipeline.dense(w("p.png"), w("m.json"), dense, cfg["dense"], w("d.h5"))
    pipeline.stage1(w("f.h5"), w("m.json"), w("s1.json"), w("s1.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=dense, dense_params=cfg["dense"],
                    dense_map_h5=w("d.h5") if dense else None)
    src = w("s1.json")
    if method == "rescu-ii":
        pipeline.limit_threads(backbone, torch=True)
        pipeline.stage2_features(w("p.png"), w("m.json"), src, w("s2.h5"), cfg["stage2"])
        pipeline.limit_threads(head, torch=True)
        pipeline.stage2_train(w("s2.h5"), src, w("head.h5"), cfg["stage2"])
        pipeline.stage2_predict(w("s2.h5"), w("head.h5"), src, w("s2.json"), w("m.json"),
                                cfg["stage2"])
        src = w("s2.json")
    pipeline.scene(w("p.png"), w("m.json"), src, w("sc.json"), w("rect"), cfg["scene"])
    pipeline.image_vp(w("p.png"), w("m.json"), w("sc.json"), w("j.json"), cfg["scene"])
    pipeline.caption(w("p.png"), w("m.json"), w("j.json"), w("final.json"), cfg["caption"],
                     claims=cfg["scene"].get("claims"))
    return io.read_json(w("final.json"))


def _text(res: rescu.ImageResult) -> str:
    return io.json_text(res)


@pytest.mark.parametrize("method", ["rescu-i", "rescu-ii"])
def test_run_in_memory_equals_the_file_pipeline(tmp_path, method):
    photo = shelf_photo(tmp_path / "shelf.png")
    cfg = load_config(stage2=method == "rescu-ii")
    # the pipeline's threads in this process too: float sums depend on the thread count
    cfg["threads"]["in_process"] = cfg["threads"]["stage2_features"]
    want = _file_chain(photo, tmp_path, cfg, method)
    got = rescu.run(photo, cfg, method=method)
    assert got.patterns and json.loads(_text(got)) == want
    # the same photo as an array: the same result but for its name
    rgb = np.asarray(Image.open(photo).convert("RGB"))
    arr = rescu.run(rgb, cfg, method=method, name="shelf.png")
    assert _text(arr) == _text(got)


def test_run_keeps_what_it_made(tmp_path):
    photo = shelf_photo(tmp_path / "shelf.png")
    ran = core.run_image(photo, method="rescu-i", keep=True)
    assert set(ran.intermediate) == {"features", "dense", "stage1", "rp_matrices", "scene",
                                     "joint"}
    assert ran.prepared.rgb.shape == (300, 520, 3) and ran.result is not None
    assert core.run_image(photo, method="rescu-i").intermediate == {}


def test_prepare_array_checks_its_input():
    small = dict(max_side=1600, min_side=16)
    with pytest.raises(InputError, match=r"uint8 RGB array, got float64 \(20, 20, 3\)"):
        core.prepare_array(np.zeros((20, 20, 3)), **small)
    with pytest.raises(InputError, match="got uint8 \\(20, 20, 4\\)"):
        core.prepare_array(np.zeros((20, 20, 4), np.uint8), **small)
    grey = core.prepare_array(np.full((20, 30), 7, np.uint8), **small)
    assert grey.rgb.shape == (20, 30, 3) and grey.failure is None
    big = core.prepare_array(np.zeros((100, 4000, 3), np.uint8), "b", max_side=1000,
                             min_side=16)
    assert big.rgb.shape == (25, 1000, 3) and big.scale_factor == 0.25
    assert big.meta["original_size"] == [4000, 100]
    tiny = core.prepare_array(np.zeros((8, 8, 3), np.uint8), "t", **small)
    assert tiny.failure["stage"] == "prepare" and "t: image too small" in tiny.failure["message"]
    with pytest.raises(InputError, match="an RGB array or a path, got list"):
        rescu.run([[0]])
    with pytest.raises(InputError, match="method must be one of"):
        rescu.run(np.zeros((32, 32, 3), np.uint8), method="rescu-iii")


def test_failures_in_memory_as_in_the_pipeline(tmp_path, monkeypatch):
    """A failed refining step keeps the previous result (degraded); a failed stage I
    leaves no pattern; a full disk is not the image's fault and propagates."""
    photo = shelf_photo(tmp_path / "shelf.png")

    def boom(*a, **k):
        raise RuntimeError("boom")

    with monkeypatch.context() as m:
        m.setattr(core, "analyse_scene", boom)
        res = rescu.run(photo, method="rescu-i")
    f = res.extra["failure"]
    assert (f["stage"], f["degraded_to"], f["message"]) == ("scene", "rescu-i", "boom")
    assert res.patterns and res.caption is not None  # image VP and caption ran on it

    with monkeypatch.context() as m:
        m.setattr(core, "stage2_train", boom)
        res = rescu.run(photo, method="rescu-ii")
    assert res.method == "rescu-ii" and res.patterns
    assert (res.extra["failure"]["stage"], res.extra["failure"]["degraded_to"]) == \
        ("stage2-train", "rescu-i")

    with monkeypatch.context() as m:
        m.setattr(core, "discover_patterns", boom)
        res = rescu.run(photo, method="rescu-ii")
    assert res.patterns == [] and res.extra["failure"]["stage"] == "rescu-i"
    assert not core.is_degraded(res.extra["failure"])

    def full(*a, **k):
        raise io.DiskFullError("no space")

    with monkeypatch.context() as m, pytest.raises(io.DiskFullError):
        m.setattr(core, "describe", full)
        rescu.run(photo, method="rescu-i")


def test_discover_writes_no_work_folder(tmp_path, monkeypatch):
    (tmp_path / "in").mkdir()
    photo = shelf_photo(tmp_path / "in" / "shelf.png")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # TMPDIR read afresh
    res = rescu.discover(photo, method="rescu-i")  # no out_dir: nothing written anywhere
    assert res.patterns and list(tmp.iterdir()) == []
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == ["shelf.png"]
    out = tmp_path / "out"
    rescu.discover(photo, out, method="rescu-i")
    assert sorted(p.name for p in out.iterdir()) == [".rescu-lock", ".rescu-results.json", "shelf.json",
                                                      "shelf.png", "shelf_rectified"]
    assert list(tmp.iterdir()) == []
    rescu.discover(photo, out, method="rescu-i", keep_work=True)
    work = sorted(p.name for p in (out / ".work" / "shelf").iterdir())
    assert work == ["dense.json", "features.h5", "final.json", "image.png", "joint.json",
                    "meta.json", "rescu-i.json", "rescu-i.rp.h5", "scene.json"]


def test_checkpoint_bytes_do_not_depend_on_the_temporary_name(tmp_path):
    """The same head written twice (to other temporary names) gives the same bytes, and
    reads back as written."""
    from rescu.extension.train import load_checkpoint, save_checkpoint

    ckpt = {"head": {"state_dict": {"0.weight": np.arange(6.0, dtype=np.float32).reshape(2, 3)},
                     "n_classes": 2, "rp_index": [0]},
            "info": {"status": "ok", "train_loss": [0.5, 0.25]}}
    save_checkpoint(tmp_path / "a.h5", ckpt)
    (tmp_path / "b").mkdir()
    save_checkpoint(tmp_path / "b" / "c.h5", ckpt)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b" / "c.h5").read_bytes()
    back = load_checkpoint(tmp_path / "a.h5")
    assert np.array_equal(back["head"]["state_dict"]["0.weight"],
                          ckpt["head"]["state_dict"]["0.weight"])
    assert back["info"] == ckpt["info"] and back["head"]["rp_index"] == [0]
    save_checkpoint(tmp_path / "f.h5", {"failure": {"stage": "stage2-train", "message": "x"}})
    assert load_checkpoint(tmp_path / "f.h5") == {"failure": {"stage": "stage2-train",
                                                              "message": "x"}}
    save_checkpoint(tmp_path / "e.h5", {"head": {"state_dict": {}, "n_classes": 1}})
    assert load_checkpoint(tmp_path / "e.h5")["head"]["state_dict"] == {}
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    for bad in ("bad.h5", "missing.h5"):
        with pytest.raises(InputError, match=bad):
            load_checkpoint(tmp_path / bad)
