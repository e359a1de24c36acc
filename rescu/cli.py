"""The ``rescu`` command: run RESCU on your own photos, evaluate predictions.

Exit codes: 0 success; 1 some images failed (their JSON records why; the others are
done; an image whose stage II failed keeps stage I's patterns); 2 bad usage,
configuration or input files; 3 an unexpected internal error.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

EXIT_OK, EXIT_IMAGE_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3
# 1 also when a step failed but the photo kept the previous step's result (its JSON's
# failure record has "degraded_to"; the summary line says so)


def _parse_set(items: Sequence[str]) -> dict[str, Any]:
    """``["stage1.max_patterns=3", ...]`` -> nested dict (values parsed as YAML).

    Raises :class:`~rescu.io.InputError` naming ``--set`` and the item when an item is
    not ``KEY=VALUE`` or its value is not YAML.
    """
    import yaml

    from .io import InputError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise InputError(f"--set expects KEY=VALUE (e.g. stage1.max_patterns=3), "
                             f"got {item!r}")
        try:
            parsed = yaml.safe_load(value)
        except yaml.YAMLError as e:
            problem = getattr(e, "problem", None) or str(e).split("\n")[0]
            raise InputError(f"--set {item!r}: the value is not valid YAML ({problem}); "
                             f"quote strings, write lists as [1, 2]") from None
        node = out
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise InputError(f"--set {item!r}: {p!r} is set to a value by an earlier --set")
            node = nxt
        node[parts[-1]] = parsed
    return out


def _collect_photos(paths: Sequence[str]) -> list[Path]:
    """The photos named on the command line (folders expanded); a note on stderr for
    entries of a folder that look like images but cannot be read (broken links, ...)."""
    from .io import IMAGE_EXTENSIONS, InputError, check_photo_file, list_images, skipped_images

    photos: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            folder = p / "images" if (p / "images").is_dir() else p
            found = list_images(folder)
            skipped = skipped_images(folder)
            if skipped:
                print(printable(f"rescu: note: skipped in {folder}: {', '.join(skipped)}"),
                      file=sys.stderr)
            subs = sorted(q.name for q in folder.iterdir()
                          if q.is_dir() and not q.name.startswith(".") and _has_images(q))
            if subs:  # a folder's photos only, not its subfolders': say so
                shown = ", ".join(subs[:5]) + (f" and {len(subs) - 5} more" if len(subs) > 5
                                               else "")
                print(printable(f"rescu: note: not searched, the subfolder(s) of {folder} "
                                f"with photos: {shown} (name them to include them)"),
                      file=sys.stderr)
            if not found:
                raise InputError(f"{p}: no image files ({', '.join(IMAGE_EXTENSIONS)}) in folder")
            photos += found
        else:
            photos.append(check_photo_file(p))
    unique: dict[Path, Path] = {}
    for p in photos:  # one photo named twice (a file and its folder) runs once
        unique.setdefault(p.resolve(), p)
    return list(unique.values())


def _has_images(folder: Path) -> bool:
    """Whether ``folder`` holds image files directly (False where it cannot be read)."""
    from .io import list_images

    try:
        return bool(list_images(folder))
    except OSError:
        return False


def printable(text: str) -> str:
    """:func:`rescu.io.printable`: control characters of file names escaped, not sent to
    the terminal."""
    from .io import printable as _p

    return _p(text)


def _parse_box(text: str, where: str) -> tuple[float, float, float, float]:
    """``"X,Y,W,H"`` -> four floats; :class:`~rescu.io.InputError` naming ``where``."""
    import math

    from .io import InputError

    parts = [t.strip() for t in str(text).split(",")]
    try:
        vals = tuple(float(t) for t in parts)
    except ValueError:
        vals = ()
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{where}: expected X,Y,W,H (four numbers, pixels of the original "
                         f"photo), got {text!r}")
    return vals  # type: ignore[return-value]


EXAMPLES_HEADER = ("file", "x", "y", "w", "h")


def read_examples_file(path: Path, photos: Sequence[Path]
                       ) -> dict[Path, list[tuple[float, float, float, float]]]:
    """The example boxes of an ``--examples`` CSV file, by photo.

    The file has the header ``file,x,y,w,h`` and one row per box (several rows for
    several boxes of one photo); ``file`` is a photo's file name (``cells.jpg``) or its
    path as given on the command line. Photos without a row run without examples.
    Raises :class:`~rescu.io.InputError` naming the file and line for a missing or
    unreadable file, another header, a row that is not five fields or whose box is not
    four finite numbers, a name that matches no photo of the run or matches two.
    """
    import csv

    from .io import InputError

    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"--examples {path}: cannot read it ({getattr(e, 'strerror', None) or e})"
                         ) from None
    rows = list(csv.reader(text.splitlines()))
    if not rows or tuple(c.strip().lower() for c in rows[0]) != EXAMPLES_HEADER:
        got = ",".join(rows[0]) if rows else "an empty file"
        raise InputError(f"--examples {path}: the first line must be the header "
                         f"{','.join(EXAMPLES_HEADER)}, got {got!r}")
    by_name: dict[str, list[Path]] = {}
    for ph in photos:
        for key in {ph.name, str(ph)}:
            by_name.setdefault(key, []).append(ph)
    out: dict[Path, list[tuple[float, float, float, float]]] = {}
    for n, row in enumerate(rows[1:], 2):
        if not row or not "".join(row).strip():
            continue
        where = f"--examples {path} line {n}"
        if len(row) != 5:
            raise InputError(f"{where}: expected 5 fields file,x,y,w,h, got {len(row)}")
        name = row[0].strip()
        match = by_name.get(name, [])
        if not match:
            raise InputError(f"{where}: {name!r} matches none of the {len(photos)} photo(s) "
                             f"given")
        if len(set(match)) > 1:
            raise InputError(f"{where}: {name!r} matches {len(set(match))} photos "
                             f"({', '.join(map(str, sorted(set(match))))}); give its path")
        out.setdefault(match[0], []).append(_parse_box(",".join(row[1:]), where))
    if not out:
        raise InputError(f"--examples {path}: no box (only the header)")
    return out


def result_names(photos: Sequence[Path]) -> list[str]:
    """The name each photo's outputs get (``<name>.json``, ``<name>.png``, ...).

    The file's stem, or its whole file name (``x.jpg`` -> ``x.jpg``) when two photos
    share a stem (``x.jpg`` and ``x.png``). Raises :class:`~rescu.io.InputError` before
    any work when names still collide (``a/x.jpg`` and ``b/x.jpg``).
    """
    from collections import Counter

    from .io import InputError

    stems = Counter(p.stem for p in photos)
    names = [p.stem if stems[p.stem] == 1 else p.name for p in photos]
    seen: dict[str, Path] = {}
    for p, n in zip(photos, names):
        if n in seen:
            raise InputError(f"{seen[n]} and {p} would write the same result files "
                             f"({n}.json); run them into different --out folders")
        seen[n] = p
    return names


def _check_out_dir(out: Path, photos: Sequence[Path]) -> None:
    """Refuse an output folder that is a file, cannot be written, or holds an input photo
    (its overlay ``<stem>.png`` or JSON could overwrite a user's file)."""
    import os

    from .io import InputError

    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    root = out.resolve()
    for p in photos:
        if p.resolve().is_relative_to(root):
            raise InputError(f"--out {out}: holds the input photo {p}; results are written "
                             f"as <name>.json / <name>.png and could overwrite your files: "
                             f"choose a folder without photos in it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"--out {out}: cannot be created ({e.strerror or e})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f"--out {out}: not writable")


def _summary_line(name: str, res: Any) -> str:
    """``<name>: <what was found> — "<caption>"`` (:func:`rescu.captions.caption.
    summary_line`: the caption's facts, counts and confidences), or the failure."""
    from .captions.caption import NO_PATTERN, summary_line

    f = res.extra.get("failure")
    note = ""
    if f and f.get("degraded_to"):  # a step failed; the previous step's patterns kept
        note = (f" [FAILED in {f.get('stage')}: {f.get('message')}; "
                f"{f.get('degraded_to')}'s result kept]")
    elif f:
        return f"{name}: FAILED in {f.get('stage')}: {f.get('message')}"
    line = summary_line(res)
    cap = (res.caption or {}).get("enhanced")
    if line == NO_PATTERN:
        return f"{name}: {line}{_set_aside(res)}{note}"
    if not cap:
        return f"{name}: {line}{note}"
    return f'{name}: {line} — "{cap}"{note}'


def _set_aside(res: Any) -> str:
    """For a photo with no RP: what the confidence set aside, if anything (the RPs of
    ``extra["candidate_patterns"]`` dropped for low confidence, two or more instances),
    and how to count what the user sees: on photos full of small objects the objects
    are often there, under the threshold (docs/studies/confidence.md).

    >>> from rescu.types import ImageResult
    >>> box = {"bbox": [0, 0, 5, 5]}
    >>> r = ImageResult(image="x", width=9, height=9, method="rescu-ii", extra={
    ...     "candidate_patterns": [
    ...         {"dropped": "low confidence", "confidence": 0.16, "instances": [box] * 9},
    ...         {"dropped": "low confidence", "confidence": 0.1, "instances": [box] * 3},
    ...         {"dropped": "one structure", "confidence": 0.5, "instances": [box] * 4}]})
    >>> _set_aside(r)
    ' Set aside under the confidence threshold: 2 candidates, the most confident 9 instances at 0.16 (candidate_patterns in the JSON); --example X,Y,W,H counts what you point at.'
    >>> _set_aside(ImageResult(image="x", width=9, height=9, method="rescu-ii"))
    ''
    """
    low = [c for c in res.extra.get("candidate_patterns") or []
           if c.get("dropped") == "low confidence" and len(c.get("instances") or []) >= 2]
    if not low:
        return ""
    best = max(low, key=lambda c: float(c.get("confidence") or 0.0))
    return (f" Set aside under the confidence threshold: {len(low)} candidate"
            f"{'s' if len(low) != 1 else ''}, the most confident "
            f"{len(best['instances'])} instances at {float(best.get('confidence') or 0):.2f}"
            " (candidate_patterns in the JSON); --example X,Y,W,H counts what you point at.")


def _terminate(signum: int, frame: Any) -> None:
    """SIGTERM: leave like Ctrl-C (the staging folder is removed, results stay whole)."""
    raise KeyboardInterrupt


def cmd_discover(args: argparse.Namespace) -> int:
    import signal

    from . import outputs
    from .config import load_config
    from .outputs import check_targets
    from .pipeline import setup_logging

    sets = (["dense.enabled=true"] if args.dense else []) \
        + (["dense.enabled=false"] if args.no_dense else []) + list(args.set)
    cfg = load_config(args.config, _parse_set(sets), stage2=args.method == "rescu-ii",
                      profile="objects" if args.objects else None)
    photos = _collect_photos(args.photos)
    names = result_names(photos)
    examples: dict[Path, list[tuple[float, float, float, float]]] = {}
    if args.example:
        boxes = [_parse_box(b, "--example") for b in args.example]
        examples = {ph: boxes for ph in photos}
    elif args.examples:
        examples = read_examples_file(Path(args.examples), photos)
    out = Path(args.out)
    _check_out_dir(out, photos)
    check_targets(out, names, force=args.force)
    signal.signal(signal.SIGTERM, _terminate)  # a kill runs the cleanup of `finally` blocks
    log = outputs.open_log(out)  # never through a link; recorded as rescu's
    try:
        setup_logging(level=logging.DEBUG if args.verbose else logging.INFO, stream=log)
        return _discover_photos(args, cfg, photos, names, examples, out)
    finally:
        logging.getLogger("rescu").handlers[:] = []
        outputs.close_log(out, log)


def _discover_photos(args: argparse.Namespace, cfg: dict[str, Any], photos: list[Path],
                     names: list[str], examples: dict[Path, Any], out: Path) -> int:
    """``rescu discover``'s loop over the photos, the gallery and the closing lines."""
    from tqdm import tqdm

    from . import outputs
    from .api import discover
    from .core import ExampleError
    from .io import DiskFullError

    log = logging.getLogger("rescu.cli")  # the run in rescu.log: what the terminal says
    log.info("rescu discover: %d photo(s), method %s, results in %s", len(photos),
             args.method, out)
    failed = degraded = 0
    refused: list[str] = []  # photos whose example boxes were refused: nothing written
    bar = tqdm(list(zip(photos, names)), desc="rescu discover", unit="image",
               disable=args.quiet or None, file=sys.stderr)
    for done, (photo, name) in enumerate(bar):
        bar.set_postfix_str(photo.name)
        try:
            res = discover(photo, out_dir=out, method=args.method, config=cfg,
                           keep_work=args.keep_work, name=name,
                           force=args.force, overlay=args.overlay,
                           examples=examples.get(photo))
        except ExampleError as e:  # this photo's boxes: the others go on
            failed += 1
            refused.append(name)
            tqdm.write(printable(f"{photo.name}: FAILED: {e}"), file=sys.stdout)
            log.warning("%s: FAILED: %s", photo, e)
            continue
        except DiskFullError as e:
            bar.close()
            print(printable(f"rescu: error: {e}; stopped at {photo} ({done} of {len(photos)} "
                            f"photo(s) done, their results in {out}/ intact); free some "
                            f"space and run again"),
                  file=sys.stderr)
            return EXIT_IMAGE_FAILED
        f = res.extra.get("failure")
        failed += bool(f) and not f.get("degraded_to")
        degraded += bool(f) and bool(f.get("degraded_to"))
        line = _summary_line(photo.name, res)
        tqdm.write(printable(line), file=sys.stdout)
        (log.warning if f else log.info)("%s", line)
    kept = (f" ({degraded} with a failed step, the previous step's result kept)"
            if degraded else "")
    from .gallery import write_gallery

    with outputs.locked(out):  # every photo of the folder's manifest, this run's first
        page = write_gallery(out, outputs.names_in(out, [n for n in names if n not in refused]))
        outputs.record_own(out, outputs.GALLERY)
    log.info("%d of %d image(s) done%s", len(photos) - failed, len(photos), kept)
    print(printable(f"{len(photos) - failed} of {len(photos)} image(s) done{kept}; results "
                    f"in {out}/ (per-image JSON, overlay PNG; log in {out / 'rescu.log'})"))
    print(printable(f"Gallery: {page}"))
    return EXIT_IMAGE_FAILED if failed or degraded else EXIT_OK


def evaluate_predictions_cli(dataset_dir: Path, pred_dir: Path, h: float | None = None,
                             out_dir: Path | None = None) -> int:
    """``rescu evaluate``: print the metrics of one prediction folder; return an exit code.

    Uses ``annotations.json`` (RP metrics and counting) and/or ``vanishing_points.json``
    (VP success rates) of ``dataset_dir``; a missing prediction counts as no detection.
    ``h`` is the IOD threshold (None: the configuration's ``evaluation.iod_h``). Writes
    per-image scores and tables to ``out_dir`` when given. Returns 0, or 2 when the
    dataset has no ground truth.
    """
    from .evaluation.core import (RP_TABLE_NOTE, EvaluationParams, evaluate_rp_dataset,
                                  frame_markdown, summary_markdown, summary_table, write_tsv)
    from .evaluation.metrics import TABLE_METRICS
    from .evaluation.count_table import counting_table
    from .evaluation.vpd import vp_frame, vp_markdown, vp_success_table
    from .io import InputError, read_json

    h = EvaluationParams().iod_h if h is None else h
    dataset_dir, pred_dir = Path(dataset_dir), Path(pred_dir)
    if not pred_dir.is_dir():
        raise InputError(f"{pred_dir}: prediction folder not found")
    has_rp = (dataset_dir / "annotations.json").is_file()
    has_vp = (dataset_dir / "vanishing_points.json").is_file()
    if not (has_rp or has_vp):
        raise InputError(f"{dataset_dir}: no annotations.json or vanishing_points.json")
    stems = {p.stem for p in pred_dir.glob("*.json")}
    if not stems:
        raise InputError(f"{pred_dir}: no prediction files (<image stem>.json) in folder")
    images = set()
    for name in ("annotations.json", "vanishing_points.json"):
        if (dataset_dir / name).is_file():
            d = read_json(dataset_dir / name)
            images |= {Path(str(im.get("file_name", ""))).stem
                       for im in (d.get("images") or []) if isinstance(im, dict)}
    if images and not stems & images:
        example = sorted(images)[0]
        raise InputError(f"{pred_dir}: none of its {len(stems)} JSON file(s) is named after an "
                         f"image of {dataset_dir} (expected e.g. {example}.json)")
    missing = sorted(images - stems)
    if missing:
        print(f"rescu: note: {len(missing)} of {len(images)} image(s) of {dataset_dir} have no "
              f"prediction in {pred_dir} (e.g. {missing[0]}.json); they count as no detection",
              file=sys.stderr)
    method = pred_dir.name or "predictions"
    if has_rp:
        scores = evaluate_rp_dataset(dataset_dir, {method: pred_dir}, h)
        summary = summary_table(scores, TABLE_METRICS)
        print(summary_markdown(summary, TABLE_METRICS, title=f"RP discovery (IOD h = {h})",
                               note=RP_TABLE_NOTE))
        counting = counting_table(dataset_dir, {method: pred_dir}, h)
        print("\n## Counting\n\n" + frame_markdown(counting))
        if out_dir is not None:
            write_tsv(scores, Path(out_dir) / "rp_scores.tsv")
            write_tsv(summary, Path(out_dir) / "rp_discovery.tsv")
            write_tsv(counting, Path(out_dir) / "counting.tsv")
    if has_vp:
        frame = vp_frame(dataset_dir, {method: pred_dir})
        if len(frame):
            success = vp_success_table(frame)
            print("\n" + vp_markdown(success))
            if out_dir is not None:
                write_tsv(frame, Path(out_dir) / "vpd_errors.tsv")
                write_tsv(success, Path(out_dir) / "vpd.tsv")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    return evaluate_predictions_cli(Path(args.dataset_dir), Path(args.pred_dir), h=args.h,
                                    out_dir=Path(args.out) if args.out else None)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rescu")
    except PackageNotFoundError:  # a source checkout that was not installed
        from . import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    from .names import METHODS, OVERLAY_MODES
    from .params import config_defaults

    p = argparse.ArgumentParser(
        prog="rescu",
        description="RESCU: discover recurring patterns in single photos and use them for 3D "
                    "scene understanding (vanishing points, translation symmetry, counts, "
                    "captions). No configuration file and no Snakemake needed.",
        epilog="Exit codes: 0 ok; 1 some images failed (see their JSON); 2 bad usage, "
               "configuration or input; 3 internal error. The full benchmark pipeline is "
               "`snakemake --cores 2` in the source checkout.")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser(
        "discover", help="find recurring patterns in photos",
        description="Run RESCU on photos (files or folders). Writes, per photo, <stem>.json "
                    "(the per-image result format of the benchmark), <stem>.png (overlay: each "
                    "pattern's instances in its own colour with a label, a legend with counts "
                    "and confidence, thin lines to the vanishing points, the caption; "
                    "--overlay) and <stem>_rectified/rp<k>.png (rectified views), prints a "
                    "one-line summary per photo and writes DIR/index.html, a page with every "
                    "photo's overlay, summary and caption. Photos that share a stem (x.jpg, "
                    "x.png) keep their extension in these names (x.jpg.json). The output "
                    "folder must not hold any of the photos; a file there that rescu did not "
                    "write is never replaced (without --force); a rerun replaces a photo's "
                    "whole result set. The whole configuration is checked before the first "
                    "photo.")
    d.add_argument("photos", nargs="+", metavar="PHOTO",
                   help="image files or folders of images (a folder's images/ subfolder is used "
                        "when present)")
    d.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (created); required")
    d.add_argument("--method", default=METHODS[0], choices=list(METHODS),
                   help="rescu-ii (default): stage I extended by the self-supervised stage II; "
                        "rescu-i: without stage II (whole objects still looked for unless "
                        "--no-dense: with it, the fast mode); grasp: the GRASP baseline")
    d.add_argument("--config", metavar="YAML", default=None,
                   help="optional YAML file overriding sections of the default configuration "
                        "(rescu/defaults/config.yaml)")
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter, e.g. --set stage1.max_patterns=2 (repeatable)")
    dense = d.add_mutually_exclusive_group()
    dense.add_argument("--dense", action="store_true",
                       help="whole objects that recur in the CNN feature map (coins, cars from "
                            "above, chess pieces) beside stage I's RPs, every RP's confidence "
                            "scored, those below dense.min_confidence or sitting on a more "
                            "confident RP's objects hidden (the default; "
                            "--set dense.enabled=true)")
    dense.add_argument("--no-dense", action="store_true",
                       help="stage I's keypoint RPs alone, not scored, as in the paper "
                            "(--set dense.enabled=false)")
    d.add_argument("--objects", action="store_true",
                   help="photos of small or smooth objects (cars from above, chess pieces, "
                        "products): RPs from the CNN feature map only, extended by stage II "
                        "from any proposal (the profile rescu/defaults/objects.yaml; --config and "
                        "--set still apply over it)")
    d.add_argument("--force", action="store_true",
                   help="replace files in DIR named like results (<stem>.json, <stem>.png, "
                        "<stem>_rectified/) that rescu did not write; without it such files "
                        "stop the run before any work (exit 2)")
    d.add_argument("--overlay", default=None, choices=list(OVERLAY_MODES),
                   help="what <stem>.png shows: boxes (instances, labels, legend, caption), "
                        "full (also the vanishing points as thin lines) or none (no picture); "
                        "default: the config's report.overlay (full)")
    ex = d.add_mutually_exclusive_group()
    ex.add_argument("--example", action="append", default=[], metavar="X,Y,W,H",
                    help="count these: a box (pixels of the original photo: top-left corner, "
                         "width, height) around one instance of what to count; repeat for a "
                         "few boxes of the same thing. Every instance is found and reported "
                         "first (the dominant RP, the caption's count), the boxes drawn with "
                         "white frames. Applies to every photo given")
    ex.add_argument("--examples", metavar="CSV", default=None,
                    help="example boxes for many photos: a CSV file with the header "
                         "file,x,y,w,h, one row per box (several rows for several boxes of "
                         "one photo), file a photo's file name; photos without a row run "
                         "without examples")
    d.add_argument("--keep-work", action="store_true",
                   help="keep intermediate files (features, RP matrices, checkpoint) in DIR/.work/")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--verbose", action="store_true", help="debug messages in DIR/rescu.log")
    d.set_defaults(func=cmd_discover)
    e = sub.add_parser(
        "evaluate", help="score predictions against ground truth",
        description="Instance- and RP-level precision/recall (IOD), counting and vanishing-point "
                    "metrics of per-image prediction JSONs against a dataset folder "
                    "(annotations.json and/or vanishing_points.json).")
    e.add_argument("dataset_dir", help="dataset folder: images/ + annotations.json / "
                                       "vanishing_points.json")
    e.add_argument("pred_dir", help="folder of <image stem>.json predictions")
    e.add_argument("--iod", dest="h", type=float, default=None, metavar="H",
                   help=f"IOD threshold (default {config_defaults('evaluation')['iod_h']})")
    e.add_argument("--h", dest="h", type=float, help=argparse.SUPPRESS)  # its old name
    e.add_argument("--out", metavar="DIR", default=None,
                   help="also write the per-image scores and tables (TSV, Markdown) here")
    e.set_defaults(func=cmd_evaluate)
    p.set_defaults(subcommands={"discover": d, "evaluate": e})
    return p


def _parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """``parser.parse_args(argv)``, but a mistyped option is named first (with the
    nearest known one) by its subcommand's usage, before a required option it hides."""
    import difflib

    args, extra = parser.parse_known_args(argv)
    sub = args.subcommands[args.command]
    if extra:
        known = [o for a in sub._actions for o in a.option_strings
                 if a.help != argparse.SUPPRESS]
        bad = extra[0].split("=", 1)[0]
        close = difflib.get_close_matches(bad, known, n=1) if bad.startswith("-") else []
        sub.error(f"unrecognized argument {extra[0]!r}"
                  + (f" (did you mean {close[0]}?)" if close else ""))
    if args.command == "discover" and args.out is None:
        sub.error("the following arguments are required: --out")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    from .io import InputError

    parser = build_parser()
    args = _parse(parser, argv)
    try:
        return int(args.func(args))
    except (InputError, ValueError, FileNotFoundError) as e:
        print(f"rescu: error: {printable(str(e))}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("rescu: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001
        import traceback

        traceback.print_exc()
        print(f"rescu: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
