"""Datasets: which images a run processes, and where their ground truth lives.

A dataset is a name and a folder in the layout of ``../shared/README.md``: ``images/``
plus ``annotations.json`` (COCO boxes; recurring-pattern ground truth) and/or
``vanishing_points.json``. A plain folder of photos (no ``images/`` subfolder, no ground
truth) works too. Two datasets are built by the pipeline itself: ``kind: synthetic``
(the generated benchmark) and ``kind: package_photos`` (photos shipped inside installed
packages).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from ..io import IMAGE_EXTENSIONS, InputError

SYNTHETIC_DIR = "data/synthetic"
PHOTOS_DIR = "data/photos"


def dataset_root(name: str, spec: dict[str, Any], results_dir: str) -> Path:
    """The folder of dataset ``name`` (generated datasets live under ``results_dir``)."""
    kind = spec.get("kind", "folder")
    if kind == "synthetic":
        return Path(results_dir) / SYNTHETIC_DIR
    if kind == "package_photos":
        return Path(results_dir) / PHOTOS_DIR
    return Path(spec["path"])


def _image_folder(root: Path) -> tuple[Path, str]:
    """``(folder holding the images, prefix of their names in the results JSON)``."""
    if (root / "images").is_dir():
        return root / "images", "images/"
    return root, ""


def selected_datasets(config: dict[str, Any]) -> set[str] | None:
    """The datasets named by the config's ``run_datasets`` (None: every enabled one).

    ``run_datasets`` is a list of names or one string of comma-separated names (what
    ``snakemake --config run_datasets=synthetic,chess`` passes). A named dataset runs even
    when its spec says ``enabled: false``. A name that is not in ``datasets`` is an
    :class:`InputError` listing the configured names; an empty selection is one too.
    """
    sel = config.get("run_datasets")
    if sel is None:
        return None
    names = [n.strip() for n in sel.split(",")] if isinstance(sel, str) else list(sel)
    names = [n for n in names if n]
    known = list(config["datasets"])
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        what = f"unknown dataset(s) {unknown}" if unknown else "names no dataset"
        raise InputError(f"config run_datasets: {what}; the configured datasets are {known}")
    return set(names)


def build_image_table(config: dict[str, Any], results_dir: str,
                      log: Callable[[str], None] = print) -> dict[str, dict[str, Any]]:
    """The images of every configured dataset, known before anything runs.

    Returns ``{dataset: {"root": Path, "kind": str, "images": {stem: path}, "names":
    {stem: "images/<file>"}, "has_rps": bool, "has_vps": bool}}``. A folder dataset
    whose folder is missing is skipped with a message (``log``); two images with the
    same stem in one dataset are an error naming both. Only the datasets of
    ``run_datasets`` are listed when it is set (:func:`selected_datasets`), otherwise
    those not marked ``enabled: false``.
    """
    from .synth import synthetic_image_names

    selected = selected_datasets(config)
    table: dict[str, dict[str, Any]] = {}
    for name, spec in config["datasets"].items():
        spec = spec or {}
        runs = name in selected if selected is not None else spec.get("enabled", True)
        if not runs:
            continue
        kind = spec.get("kind", "folder")
        root = dataset_root(name, spec, results_dir)
        limit = spec.get("max_images")
        if kind == "synthetic":
            files = synthetic_image_names(int(config["synthetic"]["n_images"]))
            folder, prefix = root / "images", "images/"
            has_rps = has_vps = True
        elif kind == "package_photos":
            files = list(config["package_photos"]["names"])
            folder, prefix = root / "images", "images/"
            has_rps = has_vps = False
        else:
            if not root.is_dir():
                log(f"rescu: dataset '{name}': folder {root} not found, skipped")
                continue
            folder, prefix = _image_folder(root)
            files = sorted(p.name for p in folder.iterdir() if p.is_file()
                           and p.suffix.lower() in IMAGE_EXTENSIONS
                           and not p.name.startswith("."))
            has_rps = (root / "annotations.json").is_file()
            has_vps = (root / "vanishing_points.json").is_file()
            if not files:
                log(f"rescu: dataset '{name}': no images in {folder}, skipped")
                continue
        if limit is not None:
            files = files[: int(limit)]
        imgs: dict[str, Path] = {}
        names: dict[str, str] = {}
        for f in files:
            stem = Path(f).stem
            if stem in imgs:
                raise InputError(f"{folder}: images '{imgs[stem].name}' and '{f}' share the "
                                 f"name '{stem}'; rename one of them")
            imgs[stem] = folder / f
            names[stem] = prefix + f
        table[name] = {"root": root, "kind": kind, "images": {s: str(p) for s, p in imgs.items()},
                       "names": names, "has_rps": has_rps, "has_vps": has_vps}
    return table
