"""Bad input gets a clear error naming the file, or a documented result; writes are atomic."""

from __future__ import annotations

import json

import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rescu import io
from rescu.config import load_config
from rescu.io import InputError


def _photo(h=120, w=160, seed=0):
    return np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)


def test_zero_byte_file(tmp_path):
    p = tmp_path / "empty.jpg"
    p.write_bytes(b"")
    with pytest.raises(InputError, match=r"empty\.jpg: empty file"):
        io.load_image(p)


def test_truncated_file(tmp_path):
    p = tmp_path / "cut.jpg"
    Image.fromarray(_photo()).save(p, quality=90)
    p.write_bytes(p.read_bytes()[:300])
    with pytest.raises(InputError, match=r"cut\.jpg: unreadable or truncated"):
        io.load_image(p)


def test_non_image_file(tmp_path):
    p = tmp_path / "notes.jpg"
    p.write_text("this is not an image")
    with pytest.raises(InputError, match=r"notes\.jpg: not an image file"):
        io.load_image(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        io.load_image(tmp_path / "nope.png")


@pytest.mark.parametrize("mode", ["L", "RGBA", "P", "I;16", "RGB"])
def test_modes_become_rgb(tmp_path, mode):
    rgb = _photo()
    im = Image.fromarray(rgb)
    if mode == "I;16":
        im = Image.fromarray(rgb[..., 0].astype(np.uint16) * 257)  # 16-bit gray
    elif mode != "RGB":
        im = im.convert(mode)
    p = tmp_path / f"x_{mode.replace(';', '')}.png"
    im.save(p)
    out = io.load_image(p)
    assert out.rgb.dtype == np.uint8 and out.rgb.shape == (120, 160, 3)
    assert out.original_size == (160, 120) and out.scale_factor == 1.0
    if mode == "I;16":  # 16-bit rescaled to the 8-bit range, not clipped
        assert out.rgb.max() > 200


def test_rgba_composited_on_white(tmp_path):
    a = np.zeros((40, 40, 4), np.uint8)  # fully transparent
    p = tmp_path / "t.png"
    Image.fromarray(a, "RGBA").save(p)
    assert (io.load_image(p).rgb == 255).all()


def test_exif_rotation_gives_displayed_orientation(tmp_path):
    rgb = _photo(100, 200)
    p = tmp_path / "rot.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise for display
    Image.fromarray(rgb).save(p, exif=exif)
    out = io.load_image(p)
    assert out.original_size == (100, 200)  # width, height as displayed
    assert "exif-rotated" in out.notes


def test_tiny_image_rejected(tmp_path):
    p = tmp_path / "tiny.png"
    Image.fromarray(_photo(10, 10)).save(p)
    with pytest.raises(InputError, match=r"tiny\.png: image too small \(10x10"):
        io.load_image(p, min_side=16)


def test_huge_image_downscaled_with_scale_factor(tmp_path):
    p = tmp_path / "huge.png"
    Image.new("RGB", (12000, 9000), (120, 130, 140)).save(p)
    # 108 MP: above the default image.max_pixels (100 MP) and Pillow's warning (89 MP)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no DecompressionBombWarning
        out = io.load_image(p, max_side=1600, max_pixels=120_000_000)
    assert max(out.rgb.shape[:2]) == 1600
    assert out.original_size == (12000, 9000)
    assert out.scale_factor == pytest.approx(1600 / 12000)


def test_list_images_skips_other_files(tmp_path):
    Image.fromarray(_photo()).save(tmp_path / "a.png")
    (tmp_path / "readme.txt").write_text("x")
    (tmp_path / ".hidden.png").write_bytes(b"")
    assert [p.name for p in io.list_images(tmp_path)] == ["a.png"]


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    p = tmp_path / "r.json"
    io.write_json(p, {"a": 1})
    with pytest.raises(TypeError):
        io.write_json(p, {"a": object()})
    assert json.loads(p.read_text()) == {"a": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["r.json"]  # no temp file left


def test_malformed_json_names_file(tmp_path):
    p = tmp_path / "annotations.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match=r"annotations\.json: malformed JSON"):
        io.load_coco_rps(p)


@pytest.mark.parametrize("doc,field", [
    ({"images": []}, "'annotations'"),
    ({"images": [{"id": 1, "file_name": "images/a.jpg"}],
      "annotations": [{"image_id": 1, "category_id": 0}]}, "'bbox'"),
    ({"images": [{"id": 1, "file_name": "images/a.jpg"}],
      "annotations": [{"image_id": 1, "category_id": 0, "bbox": [1, 2, 3]}]}, r"bbox must be"),
    ({"images": [{"id": 1, "file_name": "images/a.jpg"}],
      "annotations": [{"image_id": 7, "category_id": 0, "bbox": [1, 2, 3, 4]}]}, "image_id 7"),
])
def test_malformed_annotations_name_field(tmp_path, doc, field):
    p = tmp_path / "annotations.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=field):
        io.load_coco_rps(p)


def test_coco_rps_group_categories_with_two_or_more_boxes(tmp_path):
    doc = {"images": [{"id": 1, "file_name": "images/a.jpg"}, {"id": 2, "file_name": "images/b.jpg"}],
           "categories": [{"id": 0, "name": "pawn"}, {"id": 1, "name": "king"}],
           "annotations": [{"image_id": 1, "category_id": 0, "bbox": [0, 0, 5, 5]},
                           {"image_id": 1, "category_id": 0, "bbox": [10, 0, 5, 5]},
                           {"image_id": 1, "category_id": 1, "bbox": [20, 0, 5, 5]}]}
    p = tmp_path / "annotations.json"
    p.write_text(json.dumps(doc))
    rps = io.load_coco_rps(p)
    assert rps["images/b.jpg"] == []
    assert len(rps["images/a.jpg"]) == 1 and rps["images/a.jpg"][0].category == "pawn"
    assert len(rps["images/a.jpg"][0].boxes) == 2


def test_malformed_vanishing_points_name_field(tmp_path):
    p = tmp_path / "vanishing_points.json"
    p.write_text(json.dumps({"images": [{"file_name": "a.jpg", "width": 4, "height": 3,
                                         "vanishing_points": [{"homogeneous": [1, 2]}]}]}))
    with pytest.raises(InputError, match=r"vanishing_points\.json: images\[0\]\.vanishing_points\[0\]"):
        io.load_vanishing_points(p)


def test_malformed_config_names_file_and_field(tmp_path):
    p = tmp_path / "my.yaml"
    p.write_text("image:\n  max_side: big\n")
    with pytest.raises(InputError, match=r"my\.yaml: image\.max_side = 'big': 'big' is not of type 'integer'"):
        load_config(p)
    p.write_text("image: [unclosed\n")
    with pytest.raises(InputError, match=r"my\.yaml: malformed YAML"):
        load_config(p)
    p.write_text("datasets:\n  mine: {kind: folder}\n")
    with pytest.raises(InputError, match=r"datasets\.mine"):
        load_config(p)


def test_command_line_overrides_get_yaml_types_back():
    from rescu.config import typed_cli_overrides

    # what snakemake's BaseLoader makes of --config 'synthetic={seed: 11}' and friends
    raw = {"synthetic": {"seed": "11", "sizes": [["640", "480"]]},
           "datasets": {"cmp_facade": {"max_images": "null", "enabled": "false",
                                       "path": "../data/2024 photos"}},
           "stage1": {"P_s": "0.3", "orientation_mode": "wrapped"},
           "run_datasets": "synthetic,chess", "results_dir": "results/x"}
    t = typed_cli_overrides(raw)
    assert t["synthetic"] == {"seed": 11, "sizes": [[640, 480]]}
    assert t["datasets"]["cmp_facade"] == {"max_images": None, "enabled": False,
                                           "path": "../data/2024 photos"}
    assert t["stage1"] == {"P_s": 0.3, "orientation_mode": "wrapped"}
    assert t["run_datasets"] == "synthetic,chess" and t["results_dir"] == "results/x"
    assert raw["synthetic"]["seed"] == "11"            # input unchanged
    load_config(overrides=t)                           # and the schema accepts it


def test_run_datasets_selects_and_names_unknown_datasets(tmp_path):
    from rescu.data.datasets import build_image_table, selected_datasets

    cfg = load_config()
    assert selected_datasets(cfg) is None
    every = set(build_image_table(cfg, str(tmp_path), log=lambda m: None))
    assert "synthetic" in every and "photos" in every
    for sel in (["synthetic"], "synthetic", " synthetic, "):
        table = build_image_table({**cfg, "run_datasets": sel}, str(tmp_path))
        assert list(table) == ["synthetic"]
    # a named dataset runs even when the config switches it off
    off = {**cfg, "datasets": {**cfg["datasets"], "photos": {"kind": "package_photos",
                                                           "enabled": False}}}
    assert "photos" not in build_image_table(off, str(tmp_path), log=lambda m: None)
    assert list(build_image_table({**off, "run_datasets": ["photos"]}, str(tmp_path))) == \
        ["photos"]
    with pytest.raises(InputError, match=r"run_datasets: unknown dataset\(s\) \['chesss'\]"):
        build_image_table({**cfg, "run_datasets": "synthetic,chesss"}, str(tmp_path))
    with pytest.raises(InputError, match="run_datasets: names no dataset"):
        selected_datasets({**cfg, "run_datasets": []})


def test_skipped_datasets_are_those_that_would_run_without_images(tmp_path):
    from rescu.data.datasets import build_image_table, skipped_datasets

    (tmp_path / "empty").mkdir()
    (tmp_path / "full" / "images").mkdir(parents=True)
    io.write_image(tmp_path / "full" / "images" / "a.png", np.zeros((20, 20, 3), np.uint8))
    cfg = {**load_config(), "run_datasets": None, "datasets": {
        "examples": {"kind": "examples"}, "synthetic": {"kind": "synthetic"},
        "gone": {"path": str(tmp_path / "gone")}, "empty": {"path": str(tmp_path / "empty")},
        "full": {"path": str(tmp_path / "full")},
        "off": {"path": str(tmp_path / "off"), "enabled": False}}}
    assert skipped_datasets(cfg, str(tmp_path)) == {
        "gone": f"folder {tmp_path / 'gone'} not found",
        "empty": f"no images in {tmp_path / 'empty'}"}
    table = build_image_table(cfg, str(tmp_path), log=lambda m: None)
    assert set(table) == {"examples", "synthetic", "full"}
    # a named dataset counts when it is skipped, whatever its `enabled`
    assert skipped_datasets({**cfg, "run_datasets": "off,full"}, str(tmp_path)) == {
        "off": f"folder {tmp_path / 'off'} not found"}


def test_config_defaults_are_the_shipped_config():
    from rescu.config import DEFAULT_CONFIG, _read_yaml
    from rescu.params import config_defaults

    shipped = _read_yaml(DEFAULT_CONFIG)
    assert config_defaults("stage1") == shipped["stage1"]
    assert config_defaults("scene", "completion") == shipped["scene"]["completion"]
    d = config_defaults("stage1")
    d["P_d"] = -1  # a copy: the next caller sees the shipped value
    assert config_defaults("stage1")["P_d"] == shipped["stage1"]["P_d"]
    with pytest.raises(KeyError, match="stage1.nope"):
        config_defaults("stage1", "nope")


def test_rectified_photos_get_derived_vp_truth(tmp_path):
    from rescu import pipeline
    from rescu.data.datasets import build_image_table
    from rescu.io import load_vanishing_points

    root = tmp_path / "facades"
    (root / "images").mkdir(parents=True)
    (root / "images" / "a.jpg").write_bytes(b"")
    (root / "annotations.json").write_text(json.dumps({"images": [
        {"id": 1, "file_name": "images/a.jpg", "width": 40, "height": 30}],
        "annotations": [], "categories": []}))
    cfg = {**load_config(), "run_datasets": None,
           "datasets": {"f": {"path": str(root), "vp_truth": "rectified"},
                        "g": {"path": str(root)}}}
    table = build_image_table(cfg, str(tmp_path / "results"))
    assert table["f"]["has_vps"] and table["f"]["vp_truth"] == tmp_path / "results" / "f" / \
        "vanishing_points.json"
    assert not table["g"]["has_vps"] and table["g"]["vp_truth"] is None
    pipeline.vp_truth(str(root / "annotations.json"), str(table["f"]["vp_truth"]))
    gt = load_vanishing_points(table["f"]["vp_truth"])
    assert list(gt) == ["images/a.jpg"] and gt["images/a.jpg"]["focal_px"] is None
    assert [v.tolist() for v in gt["images/a.jpg"]["vanishing_points"]] == [[1, 0, 0],
                                                                             [0, 1, 0]]
    (root / "annotations.json").write_text(json.dumps({"images": [{"id": 1}]}))
    with pytest.raises(InputError, match=r"annotations.json: .*images\[0\] needs file_name"):
        pipeline.vp_truth(str(root / "annotations.json"), str(tmp_path / "x.json"))


# ----------------------------------------------------------------------- issue 42
def _huge_png(path, side: int) -> None:
    """A ``side`` x ``side`` grey PNG written row by row (small file, little memory)."""
    import struct
    import zlib

    comp = zlib.compressobj(9)
    row = b"\x00" + b"\x80" * side
    body = b"".join(comp.compress(row) for _ in range(side)) + comp.flush()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def test_image_above_the_pixel_limit_is_refused_from_its_header(tmp_path):
    """A 20000x20000 PNG (0.4 MB) is refused before decoding (it took 5.6 GB to decode),
    and Pillow's process-wide guard is left as it was."""
    from PIL import Image

    before = Image.MAX_IMAGE_PIXELS
    p = tmp_path / "huge.png"
    _huge_png(p, 20000)
    with pytest.raises(io.InputError, match=r"huge.png: image too large \((20000x20000 = )?"
                                            r"400.0 megapixels; the limit is image.max_pixels"):
        io.load_image(p)
    assert Image.MAX_IMAGE_PIXELS == before and before is not None
    io.load_image(_small(tmp_path), max_pixels=160 * 120)
    with pytest.raises(io.InputError, match="image.max_pixels = 100"):
        io.load_image(_small(tmp_path), max_pixels=100)


def _small(tmp_path):
    p = tmp_path / "small.png"
    Image.fromarray(_photo()).save(p)
    return p


def test_pixel_limit_is_a_per_photo_failure_record(tmp_path):
    from rescu import pipeline

    p = tmp_path / "huge.png"
    _huge_png(p, 20000)
    f = pipeline.prepare(str(p), str(tmp_path / "o.png"), str(tmp_path / "o.json"),
                         image_name="huge.png", max_side=1600, min_side=16, max_pixels=10**8)
    assert f["stage"] == "prepare" and "image too large" in f["message"]
    assert json.loads((tmp_path / "o.json").read_text())["failure"] == f


def test_no_exif_no_copy_and_no_rotation_note(tmp_path, monkeypatch):
    """exif_transpose (a full copy) runs only for an EXIF rotation; the meta no longer
    says 'exif-rotated' for every image."""
    from PIL import ImageOps

    calls = []
    real = ImageOps.exif_transpose
    monkeypatch.setattr(ImageOps, "exif_transpose", lambda im, **k: calls.append(1) or real(im, **k))
    out = io.load_image(_small(tmp_path))
    assert "exif-rotated" not in out.notes and not calls


@pytest.mark.parametrize("kind", ["broken link", "fifo", "device", "folder"])
def test_not_a_regular_file_is_named_as_such(tmp_path, kind):
    import os

    p = tmp_path / "x.png"
    if kind == "broken link":
        p.symlink_to(tmp_path / "gone.png")
        want = "broken symbolic link"
    elif kind == "fifo":
        os.mkfifo(p)
        want = "a FIFO"
    elif kind == "device":
        p = Path("/dev/null")
        want = "a device"
    else:
        p.mkdir()
        want = "a folder"
    with pytest.raises(io.InputError, match=want):
        io.load_image(p)
    if kind != "device":  # in folder mode: named on stderr, not skipped silently
        skipped = io.skipped_images(tmp_path)
        assert len(skipped) == 1 and skipped[0].startswith("x.png (") and want in skipped[0]


def test_gif_is_an_image_and_non_utf8_names_are_valid_json(tmp_path):
    from rescu import pipeline

    Image.fromarray(_photo()).save(tmp_path / "a.gif")
    assert [p.name for p in io.list_images(tmp_path)] == ["a.gif"]
    name = b"caf\xe9.png".decode("utf-8", "surrogateescape")  # a Latin-1 file name
    pipeline.prepare(str(tmp_path / "a.gif"), str(tmp_path / "o.png"), str(tmp_path / "o.json"),
                     image_name=name, max_side=1600, min_side=16)
    image = json.loads((tmp_path / "o.json").read_text())["image"]
    assert image == "caf\ufffd.png"
    image.encode("utf-8")  # strict: no lone surrogate (was '\udce9')
