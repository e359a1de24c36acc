"""A small Python API: run RESCU on one photo without Snakemake.

>>> from rescu import discover                       # doctest: +SKIP
>>> result = discover("shelf.jpg", out_dir="out")    # doctest: +SKIP
>>> result.patterns[0].count, result.caption["enhanced"]   # doctest: +SKIP

It runs the same steps as the pipeline, in memory (:func:`rescu.core.run_image`), writes
the results when asked, and returns the final :class:`~rescu.types.ImageResult`. For an
RGB array and no file at all, :func:`rescu.run`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from . import core, io, outputs
from .config import load_config
from .io import InputError
from .names import METHODS, OVERLAY_MODES
from .types import ImageResult



def discover(image: str | Path, out_dir: str | Path | None = None, method: str = "rescu-ii",
             config: dict[str, Any] | None = None, keep_work: bool = False,
             name: str | None = None,
             force: bool = False, overlay: str | None = None,
             examples: Any = None) -> ImageResult:
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
    force : bool
        Replace files in ``out_dir`` that rescu did not write (never ``image`` itself).
    overlay : {"full", "boxes", "none"}, optional
        What ``<stem>.png`` shows (:data:`rescu.visualize.OVERLAY_MODES`; ``"none"``:
        no picture); None: the config's ``report.overlay``.
    examples : sequence of (x, y, w, h), optional
        "Count these": one or a few boxes of the thing to count, pixels of the original
        photo (top-left corner, width, height). The result's first pattern is then every
        instance of it, dominant (the caption counts it), its ``extra["source"]``
        ``"prompt"``, the examples' instances ``source`` ``"example"``, the others
        ``"prompt"``; with the config's ``prompt.unprompted`` the RPs found without the
        examples follow it.

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
        file rescu did not write (:class:`rescu.outputs.OverwriteError`); an example box
        is not four numbers, is smaller than ``prompt.min_box_px`` or leaves the photo
        (:class:`rescu.core.ExampleError`, naming the photo and the box; nothing written).
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

    The same photo, one of the five copies given as an example:

    >>> result = discover(photo, method="rescu-i", examples=[truth[0]])
    >>> result.patterns[0].extra["source"], result.patterns[0].count
    ('prompt', 5)
    """
    import os

    from .config import validate_config

    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(image, (str, os.PathLike)):
        raise TypeError(f"image must be a path (str or os.PathLike), got "
                        f"{type(image).__name__} {image!r}")
    if overlay is not None and overlay not in OVERLAY_MODES:
        raise InputError(f"overlay must be one of {OVERLAY_MODES}, got {overlay!r}")
    image = Path(image)
    try:
        io.check_photo_file(image)
    except InputError as e:  # missing or a broken link: FileNotFoundError, as open() does
        raise (InputError(e) if image.exists() else FileNotFoundError(str(e))) from None
    if config is None:
        cfg = load_config(stage2=method == "rescu-ii")
    else:  # checked once per content in a process (a batch: one check)
        cfg = validate_config(config, "config", stage2=method == "rescu-ii")
    stem = outputs.check_name(image.stem if name is None else name)
    if out_dir is not None:
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise InputError(f"out_dir {out_dir}: exists and is not a folder")
        if any((out / rel).resolve() == image.resolve() for rel in outputs.result_files(stem)) \
                or image.resolve().is_relative_to((out / f"{stem}_rectified").resolve()):
            raise InputError(f"out_dir {out_dir}: the results of {image} would overwrite it; "
                             f"choose another out_dir")
        outputs.check_targets(out, [stem], force=force, own=False)
        out.mkdir(parents=True, exist_ok=True)
        outputs.sweep_stale_work(out)
    mode = overlay or cfg["report"]["overlay"]
    try:
        if out_dir is None:  # nothing is written
            return _run(image, cfg, method, None, None, stem, False, mode, examples)
        with outputs.staging(out_dir) as staged:
            return _run(image, cfg, method, staged, out_dir, stem, keep_work, mode, examples)
    except io.DiskFullError:
        raise
    except OSError as e:  # a result that cannot be written: this photo fails, not the run
        from .types import failure_record

        rec = failure_record("write", e)
        return core.empty_result({"image": io.display_name(image.name)}, method, rec)


def _run(image: Path, cfg: dict[str, Any], method: str, staged: Path | None,
         out_dir: str | Path | None, stem: str, keep_work: bool, overlay: str,
         examples: Any = None) -> ImageResult:
    """:func:`discover`'s computation (:func:`rescu.core.run_image`, in memory); with
    ``out_dir`` (and its staging folder ``staged``; both None: nothing is written), the
    result set made under ``staged`` (the overlay picture drawn in mode ``overlay``, none
    for ``"none"``) and committed."""
    ran = core.run_image(image, cfg, method, name=image.name, keep=keep_work,
                         examples=examples)
    result = ran.result
    if out_dir is None or staged is None:  # both None together (discover)
        return result
    if keep_work:
        _write_work(outputs.safe_dir(out_dir, f".work/{stem}"), ran)  # no link followed
    io.write_json(staged / f"{stem}.json", result)
    if not ran.prepared.failure:
        rect = staged / f"{stem}_rectified"
        rect.mkdir()
        for pid, view in ran.rectified.items():
            io.write_image(rect / f"rp{pid}.png", view)
    if overlay != "none":
        from . import visualize

        io.write_image(staged / f"{stem}.png",
                       visualize.overlay(ran.prepared.rgb, ran.prepared.scale_factor, result,
                                         mode=overlay))
    outputs.commit(out_dir, stem, staged, io.display_name(str(image)))
    return result


def _write_work(work: Path, ran: core.RunOutput) -> None:
    """``keep_work``: the intermediate records as the pipeline's per-image files
    (``image.png``, ``meta.json``, ``features.h5``, ``dense.json``, ``rescu-i.json`` or
    ``grasp.json`` with its ``.rp.h5``, ``stage2.h5``, ``head.h5``, ``rescu-ii.json``,
    ``scene.json``, ``joint.json``, ``final.json``), those of the steps that ran."""
    from .discovery import features as F
    from .discovery import stage1 as S1

    work.mkdir(parents=True, exist_ok=True)
    kept = ran.intermediate
    io.write_image(work / "image.png", ran.prepared.rgb)
    io.write_json(work / "meta.json", ran.prepared.meta)
    if "features" in kept:
        F.save_features(work / "features.h5", kept["features"])
    if "dense" in kept:
        io.write_json(work / "dense.json", kept["dense"])
    if "stage1" in kept:
        s1 = kept["stage1"].method
        io.write_json(work / f"{s1}.json", kept["stage1"])
        S1.save_rps(work / f"{s1}.rp.h5", kept["rp_matrices"])
    if "stage2_features" in kept:
        io.write_h5(work / "stage2.h5", kept["stage2_features"])
    if "head" in kept:
        from .extension.train import save_checkpoint

        save_checkpoint(work / "head.h5", kept["head"])
    for name in ("rescu-ii", "scene", "joint"):
        if name in kept:
            io.write_json(work / f"{name}.json", kept[name])
    io.write_json(work / "final.json", ran.result)
