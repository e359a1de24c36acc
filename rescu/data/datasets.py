"""Datasets: which images a run processes, and where their ground truth lives.

A dataset is a name and a folder in the layout of ``../shared/README.md``: ``images/``
plus ``annotations.json`` (COCO boxes; recurring-pattern ground truth) and/or
``vanishing_points.json``. A plain folder of photos (no ``images/`` subfolder, no ground
truth) works too. A folder of *rectified* photos (facades seen frontally, e.g. the CMP
facade database) can say ``vp_truth: rectified``: its VP ground truth is then derived
(:func:`rectified_vp_truth`, written under the results folder): a rectified image's rows
and columns meet at the horizontal and the vertical point at infinity. Two datasets are built by the pipeline itself: ``kind: synthetic``
(the generated benchmark) and ``kind: package_photos`` (photos shipped inside installed
packages). ``kind: examples`` is the folder of real photos with ground truth shipped
inside RESCU itself (:mod:`rescu.data.examples`), read where it is installed.
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
    if kind == "examples":
        from .examples import examples_dir

        return examples_dir()
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


def skipped_datasets(config: dict[str, Any], results_dir: str) -> dict[str, str]:
    """The datasets that would run (:func:`selected_datasets`, else those enabled) but
    are skipped, each with the reason: ``{name: "folder <path> not found"}`` or ``{name:
    "no images in <folder>"}``; what :func:`build_image_table` leaves out.

    >>> skipped_datasets({"datasets": {"mine": {"path": "/no/such/folder"}}}, "results")
    {'mine': 'folder /no/such/folder not found'}
    """
    selected = selected_datasets(config)
    out: dict[str, str] = {}
    for name, spec in config["datasets"].items():
        spec = spec or {}
        runs = name in selected if selected is not None else spec.get("enabled", True)
        if not runs or spec.get("kind", "folder") != "folder":
            continue
        root = dataset_root(name, spec, results_dir)
        if not root.is_dir():
            out[name] = f"folder {root} not found"
            continue
        folder, _ = _image_folder(root)
        if not any(p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                   and not p.name.startswith(".") for p in folder.iterdir()):
            out[name] = f"no images in {folder}"
    return out


def build_image_table(config: dict[str, Any], results_dir: str,
                      log: Callable[[str], None] = print) -> dict[str, dict[str, Any]]:
    """The images of every configured dataset, known before anything runs.

    Returns ``{dataset: {"root": Path, "kind": str, "images": {stem: path}, "names":
    {stem: "images/<file>"}, "has_rps": bool, "has_vps": bool, "vp_truth": Path | None}}``;
    ``vp_truth`` is the dataset's ``vanishing_points.json`` (for ``vp_truth: rectified``
    the derived one, ``<results_dir>/<dataset>/vanishing_points.json``). A folder dataset
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
            has_vps = (root / "vanishing_points.json").is_file() or (
                spec.get("vp_truth") == "rectified" and has_rps)
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
        truth = None
        if has_vps:
            truth = (Path(results_dir) / name / "vanishing_points.json"
                     if spec.get("vp_truth") == "rectified" else root / "vanishing_points.json")
        table[name] = {"root": root, "kind": kind, "images": {s: str(p) for s, p in imgs.items()},
                       "names": names, "has_rps": has_rps, "has_vps": has_vps,
                       "vp_truth": truth}
    return table


def rectified_vp_truth(annotations: dict[str, Any]) -> dict[str, Any]:
    """VP ground truth of rectified photos, from their COCO ``annotations`` (image sizes).

    In a rectified photo of a facade the rows of the facade are horizontal and its
    columns vertical in the image: they meet at the horizontal and the vertical points at
    infinity. Each image gets those two VPs (``homogeneous`` ``[1, 0, 0]`` and ``[0, 1, 0]``,
    directions ``[1, 0, 0]`` and ``[0, 1, 0]``) and no focal length, in the format of
    ``vanishing_points.json`` (``../shared/README.md``).

    >>> t = rectified_vp_truth({"images": [{"file_name": "images/a.jpg", "width": 4,
    ...                                      "height": 3}]})
    >>> [v["homogeneous"] for v in t["images"][0]["vanishing_points"]]
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """
    if not isinstance(annotations, dict) or not isinstance(annotations.get("images"), list):
        raise InputError("annotations: field 'images' missing or not a list")
    out = []
    for i, im in enumerate(annotations["images"]):
        if not isinstance(im, dict) or not all(k in im for k in ("file_name", "width",
                                                                   "height")):
            raise InputError(f"annotations: images[{i}] needs file_name, width and height")
        vps = [{"direction": d, "homogeneous": d} for d in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])]
        out.append({"file_name": im["file_name"], "width": int(im["width"]),
                    "height": int(im["height"]), "focal_px": None, "principal_point": None,
                    "vanishing_points": vps})
    return {"derived_from": "rectified photos: rows horizontal, columns vertical",
            "images": out}
