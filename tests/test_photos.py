"""Tests of rescu.data.photos (package photos exported as a dataset)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rescu.io import load_image
from rescu.data.photos import PACKAGE_PHOTOS, PHOTO_NOTES, export_package_photos, package_photo_dir


def test_export_all_photos(tmp_path: Path) -> None:
    paths = export_package_photos(PACKAGE_PHOTOS, tmp_path)
    assert paths == [tmp_path / "images" / n for n in PACKAGE_PHOTOS]
    assert 5 <= len(paths) <= 8 and set(PHOTO_NOTES) == set(PACKAGE_PHOTOS)
    for p in paths:
        assert p.read_bytes() == (package_photo_dir() / p.name).read_bytes()
        im = load_image(p)
        assert im.rgb.ndim == 3 and min(im.original_size) >= 150
    assert sorted(x.name for x in (tmp_path / "images").iterdir()) == sorted(PACKAGE_PHOTOS)


def test_export_subset_and_default(tmp_path: Path) -> None:
    assert export_package_photos(["coins.png"], tmp_path) == [tmp_path / "images/coins.png"]
    assert (tmp_path / "images/coins.png").stat().st_size > 1000
    assert [p.name for p in export_package_photos(out_dir=tmp_path / "all")] == \
        list(PACKAGE_PHOTOS)


def test_unknown_name_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"unknown package photo\(s\) \['nope.png'\]"):
        export_package_photos(["coins.png", "nope.png"], tmp_path)
    assert not (tmp_path / "images" / "coins.png").exists()
    with pytest.raises(ValueError, match="list of file names"):
        export_package_photos("coins.png", tmp_path)  # type: ignore[arg-type]
