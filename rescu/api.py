"""A small Python API: run RESCU on one photo without Snakemake.

>>> from rescu import discover                       # doctest: +SKIP
>>> result = discover("shelf.jpg", out_dir="out")    # doctest: +SKIP
>>> result.patterns[0].count, result.caption["enhanced"]   # doctest: +SKIP

It runs the same per-image steps as the pipeline (:mod:`rescu.pipeline`), in order, in a
work folder, and returns the final :class:`~rescu.types.ImageResult`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from . import io, outputs, pipeline
from .config import load_config
from .io import InputError
from .names import METHODS
from .types import ImageResult


def _dense_step(cfg: dict[str, Any], w: Any) -> None:
    """The pipeline's dense step with its thread count (config ``threads``, as in the
    workflow), the caller's torch / OpenCV thread settings restored afterwards."""
    import cv2
    import torch

    restore = (torch.get_num_threads(), cv2.getNumThreads())
    pipeline.limit_threads((cfg.get("threads") or {}).get("stage2_features", 2), torch=True)
    try:
        pipeline.dense(w("image.png"), w("meta.json"), w("dense.json"), cfg["dense"])
    finally:
        torch.set_num_threads(restore[0])
        cv2.setNumThreads(restore[1])


def discover(image: str | Path, out_dir: str | Path | None = None, method: str = "rescu-ii",
             config: dict[str, Any] | None = None, keep_work: bool = False,
             name: str | None = None, validated: bool = False,
             force: bool = False, overlay: str | None = None) -> ImageResult:
    """Discover the recurring patterns of one photo and describe the scene.

    Parameters
    ----------
    image : path
        The photo (any format Pillow reads).
    out_dir : path, optional
        When given, ``<stem>.json`` (the per-image result), ``<stem>.png`` (the overlay
        picture) and ``<stem>_rectified/`` (rectified views) are written there, as one
        set: a rerun replaces the whole set (:mod:`rescu.outputs`).
    method : {"rescu-ii", "rescu-i", "grasp"}
        Which instances the scene analysis and caption use.
    config : dict, optional
        A full configuration (see :func:`rescu.config.load_config`); the default
        configuration when omitted.
    keep_work : bool
        Keep the intermediate files (features, RP matrices, checkpoints) in
        ``out_dir/.work/<stem>``.
    name : str, optional
        The name of the output files instead of the photo's stem (``<name>.json``, ...);
        a plain file name (no folder part).
    validated : bool
        ``config`` was already checked by :func:`rescu.config.validate_config` (the CLI
        checks it once for all photos); otherwise it is checked here.
    force : bool
        Replace files in ``out_dir`` that rescu did not write (never ``image`` itself).
    overlay : {"full", "boxes", "none"}, optional
        What ``<stem>.png`` shows (:data:`rescu.visualize.OVERLAY_MODES`; ``"none"``:
        no picture); None: the config's ``report.overlay``.

    Returns
    -------
    ImageResult
        With ``extra["failure"]`` set (and no pattern) when the image could not be
        processed (unreadable, too small, too large, stage I failed) or its results could
        not be written (``stage`` ``"write"``): this function does not raise for a bad
        image. When a later step failed (stage II, scene, image VP, caption), the
        previous step's patterns are kept and the record has ``"degraded_to"`` (see
        :func:`rescu.pipeline.is_degraded`).

    Raises
    ------
    FileNotFoundError
        ``image`` does not exist (or is a broken symbolic link).
    TypeError
        ``image`` is not a path.
    rescu.io.InputError
        ``image`` is a folder, FIFO or device; ``method`` or ``config`` is invalid (the
        message names the key and its value); ``name`` leaves ``out_dir``; ``out_dir``
        is a file, or its results would overwrite ``image`` or, without ``force``, a
        file rescu did not write (:class:`rescu.outputs.OverwriteError`).
    rescu.io.DiskFullError
        No space left while writing (the results written before are intact).

    Examples
    --------
    On a tiny synthetic photo (one row of 5 copies), stage I only:

    >>> import tempfile, cv2
    >>> from rescu.data.example import example_image
    >>> img, truth = example_image()
    >>> photo = f"{tempfile.mkdtemp()}/row.png"
    >>> cv2.imwrite(photo, img[:, :, ::-1])
    True
    >>> result = discover(photo, method="rescu-i")
    >>> "failure" in result.extra, result.patterns[0].count
    (False, 5)
    """
    import os

    from .config import validate_config

    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(image, (str, os.PathLike)):
        raise TypeError(f"image must be a path (str or os.PathLike), got "
                        f"{type(image).__name__} {image!r}")
    if overlay is not None and overlay not in ("full", "boxes", "none"):
        raise InputError(f"overlay must be 'full', 'boxes' or 'none', got {overlay!r}")
    image = Path(image)
    try:
        io.check_photo_file(image)
    except InputError as e:  # missing or a broken link: FileNotFoundError, as open() does
        raise (InputError(e) if image.exists() else FileNotFoundError(str(e))) from None
    if config is None:
        cfg = load_config(stage2=method == "rescu-ii")
    else:
        cfg = config if validated else validate_config(config, "config",
                                                       stage2=method == "rescu-ii")
    stem = outputs.check_name(image.stem if name is None else name)
    if out_dir is not None:
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise InputError(f"out_dir {out_dir}: exists and is not a folder")
        if any((out / rel).resolve() == image.resolve() for rel in outputs.result_files(stem)) \
                or image.resolve().is_relative_to((out / f"{stem}_rectified").resolve()):
            raise InputError(f"out_dir {out_dir}: the results of {image} would overwrite it; "
                             f"choose another out_dir")
        outputs.check_targets(out, [stem], force=force)
        out.mkdir(parents=True, exist_ok=True)
        outputs.sweep_stale_work(out)
    try:
        with outputs.staging(out_dir) as staged:
            return _run(image, cfg, method, staged, out_dir, stem, keep_work,
                        overlay or cfg["report"]["overlay"])
    except io.DiskFullError:
        raise
    except OSError as e:  # a result that cannot be written: this photo fails, not the run
        from .pipeline import empty_result
        from .types import failure_record

        rec = failure_record("write", e)
        return empty_result({"image": io.display_name(image.name)}, method, rec)


def _run(image: Path, cfg: dict[str, Any], method: str, staged: Path,
         out_dir: str | Path | None, stem: str, keep_work: bool, overlay: str) -> ImageResult:
    """:func:`discover`'s steps, the new result set made under ``staged`` and committed
    (the overlay picture drawn in mode ``overlay``, none for ``"none"``)."""
    if out_dir is not None and keep_work:
        work = Path(out_dir) / ".work" / stem
        work.mkdir(parents=True, exist_ok=True)
    else:
        work = staged / "work"
        work.mkdir()
    w = lambda name: str(work / name)  # noqa: E731
    pipeline.prepare(str(image), w("image.png"), w("meta.json"), image_name=image.name,
                     max_side=cfg["image"]["max_side"], min_side=cfg["image"]["min_side"],
                     max_pixels=cfg["image"]["max_pixels"])
    meta = io.read_json(w("meta.json"))
    if meta.get("failure"):  # nothing to process: no step past this one needs to run
        result = pipeline.empty_result(meta, method, meta["failure"])
        io.write_json(w("final.json"), result)
    else:
        result = _steps(cfg, method, w, staged / f"{stem}_rectified")
    if out_dir is not None:
        io.write_json(staged / f"{stem}.json", result)
        if overlay != "none":
            pipeline.overlay(w("image.png"), w("meta.json"), w("final.json"),
                             str(staged / f"{stem}.png"), mode=overlay)
        outputs.commit(out_dir, stem, staged, io.display_name(str(image)))
    return result


def _steps(cfg: dict[str, Any], method: str, w: Any, rect: Path) -> ImageResult:
    """The steps after ``prepare`` on a prepared photo; the final result."""
    pipeline.features(w("image.png"), w("meta.json"), w("features.h5"), cfg["features"])
    s1 = "grasp" if method == "grasp" else "rescu-i"
    dense = s1 == "rescu-i" and bool(cfg["dense"]["enabled"])
    if dense:
        _dense_step(cfg, w)
    pipeline.stage1(w("features.h5"), w("meta.json"), w(f"{s1}.json"), w(f"{s1}.rp.h5"),
                    cfg["grasp"] if s1 == "grasp" else cfg["stage1"], method=s1,
                    png=w("image.png"), dense_json=w("dense.json") if dense else None,
                    dense_params=cfg["dense"])
    source = w(f"{s1}.json")
    if method == "rescu-ii":
        # the pipeline's thread counts (config `threads`): the same floats as its run,
        # and no threads spinning against each other on a busy machine
        import cv2
        import torch

        threads = cfg.get("threads") or {}
        restore = (torch.get_num_threads(), cv2.getNumThreads())
        pipeline.limit_threads(threads.get("stage2_features", 2), torch=True)
        try:
            pipeline.stage2_features(w("image.png"), w("meta.json"), source, w("stage2.h5"),
                                     cfg["stage2"])
            pipeline.limit_threads(threads.get("stage2_head", 1), torch=True)
            pipeline.stage2_train(w("stage2.h5"), source, w("head.pt"), cfg["stage2"])
            pipeline.stage2_predict(w("stage2.h5"), w("head.pt"), source, w("rescu-ii.json"),
                                    w("meta.json"), cfg["stage2"])
        finally:
            torch.set_num_threads(restore[0])  # the caller's settings back
            cv2.setNumThreads(restore[1])
        source = w("rescu-ii.json")
    pipeline.scene(w("image.png"), w("meta.json"), source, w("scene.json"), str(rect),
                   cfg["scene"])
    pipeline.image_vp(w("image.png"), w("meta.json"), w("scene.json"), w("joint.json"),
                      cfg["scene"])
    pipeline.caption(w("image.png"), w("meta.json"), w("joint.json"), w("final.json"),
                     cfg["caption"], claims=cfg["scene"].get("claims"))
    return io.read_result(w("final.json"))
