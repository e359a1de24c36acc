"""Tests of rescu.data.examples: the example photos shipped with RESCU, credited."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rescu.config import load_config
from rescu.data.datasets import build_image_table
from rescu.data.examples import LICENSED_SETS, build_examples, examples_dir
from rescu.io import load_coco_rps, load_image

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NEVER = ("cmp_facade", "aerial_cars", "york_urban")  # their licences do not allow it


def _shipped() -> list[Path]:
    return sorted((examples_dir() / "images").iterdir())


def test_a_dozen_small_photos_of_several_kinds_ship() -> None:
    photos = _shipped()
    assert 8 <= len(photos) <= 16
    assert sum(p.stat().st_size for p in photos) < 5e6          # a few MB in all
    kinds = {p.stem.rsplit("-", 1)[0] for p in photos}
    assert kinds <= set(LICENSED_SETS) and len(kinds) >= 5
    for p in photos:
        im = load_image(p)
        assert max(im.original_size) <= 800 and min(im.original_size) >= 200


def test_every_photo_is_credited_with_its_source_and_licence() -> None:
    credits = (examples_dir() / "CREDITS.md").read_text()
    rows = [r for r in credits.splitlines() if r.startswith("| `images/")]
    assert len(rows) == len(_shipped())
    for p, row in zip(_shipped(), sorted(rows)):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[0] == f"`images/{p.name}`"
        source, licence = LICENSED_SETS[cells[1]]
        assert cells[3] == source and cells[4] == licence
    for name in NEVER:
        assert name not in LICENSED_SETS and name not in credits


def test_the_ground_truth_names_every_photo_and_what_a_person_counts() -> None:
    ann = json.loads((examples_dir() / "annotations.json").read_text())
    assert sorted(Path(im["file_name"]).name for im in ann["images"]) == \
        [p.name for p in _shipped()]
    for im in ann["images"]:
        if im["dataset"] in ("blood_cells", "nuclei", "parking_lot", "aquarium"):
            assert im["count_class"]
    rps = load_coco_rps(examples_dir() / "annotations.json")
    assert all(rps[f] for f in rps)                     # every photo has a recurring pattern
    for im in ann["images"]:                            # boxes inside the (shrunk) photos
        boxes = [a["bbox"] for a in ann["annotations"] if a["image_id"] == im["id"]]
        assert boxes and all(x >= -1 and y >= -1 and x + w <= im["width"] + 1
                             and y + h <= im["height"] + 1 for x, y, w, h in boxes)


def test_the_default_run_reads_them_where_rescu_is_installed(tmp_path: Path) -> None:
    cfg = load_config(None)
    assert list(cfg["datasets"])[0] == "examples"
    cfg["run_datasets"] = ["examples"]
    table = build_image_table(cfg, str(tmp_path), log=lambda m: None)
    ex = table["examples"]
    assert ex["root"] == examples_dir() and ex["has_rps"] and not ex["has_vps"]
    assert sorted(Path(p).name for p in ex["images"].values()) == [p.name for p in _shipped()]
    assert all(n.startswith("images/") for n in ex["names"].values())


def test_only_licensed_sets_may_ship(tmp_path: Path) -> None:
    for name in NEVER:
        with pytest.raises(ValueError, match="may ship"):
            build_examples(tmp_path, tmp_path / "out", sets=(name,))
    assert not (tmp_path / "out").exists()


@pytest.mark.shared
@pytest.mark.skipif(not (SHARED / "blood_cells").is_dir(),
                    reason="needs ../shared/data (the evaluation sets)")
def test_the_shipped_folder_is_what_the_builder_makes(tmp_path: Path) -> None:
    """The maintainer's command remakes the shipped folder: the same photos (sizes), the
    same boxes, the same credits."""
    build_examples(SHARED, tmp_path)
    assert (tmp_path / "CREDITS.md").read_text() == (examples_dir() / "CREDITS.md").read_text()
    assert json.loads((tmp_path / "annotations.json").read_text()) == \
        json.loads((examples_dir() / "annotations.json").read_text())
    for p in _shipped():
        a, b = load_image(p), load_image(tmp_path / "images" / p.name)
        assert a.original_size == b.original_size
