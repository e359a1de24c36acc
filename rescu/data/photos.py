"""Real photos shipped inside scikit-image's package folder, exported as a small dataset.

These files are part of the scikit-image wheel (no download): they give the pipeline a
few real images to run on without ``../shared``. Some show recurrence (coins in a grid,
bricks in a wall under perspective, chessboard squares, lines of printed text); two are
smoke tests with little recurrence (a coffee cup, a portrait).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["PACKAGE_PHOTOS", "PHOTO_NOTES", "package_photo_dir", "export_package_photos"]

#: Photos exported by default, in this order.
PACKAGE_PHOTOS: tuple[str, ...] = (
    "coins.png", "brick.png", "chessboard_RGB.png", "page.png", "coffee.png",
    "astronaut.png",
)

#: What each photo is good for.
PHOTO_NOTES: dict[str, str] = {
    "coins.png": "24 coins in a 4 x 6 grid, grey, 384x303: a frontal recurring pattern",
    "brick.png": "brick wall under perspective, grey, 512x512: recurrence with a finite VP",
    "chessboard_RGB.png": "8 x 8 chessboard, 200x200: recurring squares, little texture",
    "page.png": "printed page, grey, 384x191: recurring letters and text lines",
    "coffee.png": "coffee cup on a table, 600x400: smoke test with little recurrence",
    "astronaut.png": "portrait of an astronaut, 512x512: smoke test (patches on the suit)",
}


def package_photo_dir() -> Path:
    """Folder of scikit-image's bundled data files (``skimage/data``)."""
    import skimage.data

    return Path(os.path.dirname(skimage.data.__file__))


def export_package_photos(names: list[str] | tuple[str, ...] = PACKAGE_PHOTOS,
                          out_dir: str | os.PathLike[str] = ".") -> list[Path]:
    """Copy package photos byte for byte to ``out_dir/images/`` (atomic writes).

    Parameters
    ----------
    names : sequence of str
        File names from :data:`PACKAGE_PHOTOS` (e.g. ``"coins.png"``).
    out_dir : path
        Dataset folder; the photos go to ``out_dir/images/<name>``.

    Returns
    -------
    list of Path
        The written files, in the order of ``names``.

    Raises
    ------
    ValueError
        For a name not in :data:`PACKAGE_PHOTOS` (the message lists the known names).
    FileNotFoundError
        If scikit-image's package folder lacks the file.
    """
    from ..io import atomic_path

    if isinstance(names, str):
        raise ValueError(f"names must be a list of file names, got the string {names!r}")
    unknown = [n for n in names if n not in PACKAGE_PHOTOS]
    if unknown:
        raise ValueError(f"unknown package photo(s) {unknown}; known photos are "
                         f"{list(PACKAGE_PHOTOS)}")
    src_dir = package_photo_dir()
    dest = Path(out_dir) / "images"
    written = []
    for n in names:
        src = src_dir / n
        if not src.is_file():
            raise FileNotFoundError(f"{src}: missing from scikit-image's package folder")
        with atomic_path(dest / n) as tmp:
            tmp.write_bytes(src.read_bytes())
        written.append(dest / n)
    return written
