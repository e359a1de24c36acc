"""The ``rescu`` command: run RESCU on your own photos, evaluate predictions.

Exit codes: 0 success; 1 some images failed (their JSON records why; the others are
done); 2 bad usage, configuration or input files; 3 an unexpected internal error.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

EXIT_OK, EXIT_IMAGE_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3


def _parse_set(items: Sequence[str]) -> dict[str, Any]:
    """``["stage1.max_patterns=3", ...]`` -> nested dict (values parsed as YAML)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set expects KEY=VALUE (e.g. stage1.max_patterns=3), got {item!r}")
        key, value = item.split("=", 1)
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = yaml.safe_load(value)
    return out


def _collect_photos(paths: Sequence[str]) -> list[Path]:
    from .io import IMAGE_EXTENSIONS, InputError, list_images

    photos: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = list_images(p / "images" if (p / "images").is_dir() else p)
            if not found:
                raise InputError(f"{p}: no image files ({', '.join(IMAGE_EXTENSIONS)}) in folder")
            photos += found
        elif p.exists():
            photos.append(p)
        else:
            raise InputError(f"{p}: file not found")
    return photos


def _summary_line(name: str, res: Any) -> str:
    f = res.extra.get("failure")
    if f:
        return f"{name}: FAILED in {f.get('stage')}: {f.get('message')}"
    if not res.patterns:
        return f"{name}: no recurring pattern"
    parts = [f"{len(res.patterns)} RP(s), counts " + ",".join(str(p.count) for p in res.patterns)]
    if res.vanishing_point is not None:
        parts.append("VP " + ("inside" if res.vanishing_point.inside_image else "outside")
                     + " the image")
    if any(p.translation_symmetry and p.translation_symmetry.detected for p in res.patterns):
        parts.append("translation symmetry")
    cap = (res.caption or {}).get("enhanced")
    line = f"{name}: " + "; ".join(parts)
    return line + (f' — "{cap}"' if cap else "")


def cmd_discover(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .api import discover
    from .config import load_config
    from .pipeline import setup_logging

    cfg = load_config(args.config, _parse_set(args.set))
    photos = _collect_photos(args.photos)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    setup_logging(str(out / "rescu.log"), logging.DEBUG if args.verbose else logging.INFO)
    failed = 0
    bar = tqdm(photos, desc="rescu discover", unit="image", disable=args.quiet or None,
               file=sys.stderr)
    for photo in bar:
        bar.set_postfix_str(photo.name)
        res = discover(photo, out_dir=out, method=args.method, config=cfg,
                       keep_work=args.keep_work)
        failed += bool(res.extra.get("failure"))
        tqdm.write(_summary_line(photo.name, res), file=sys.stdout)
    print(f"{len(photos) - failed} of {len(photos)} image(s) done; results in {out}/ "
          f"(per-image JSON, overlay PNG; log in {out / 'rescu.log'})")
    return EXIT_IMAGE_FAILED if failed else EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_predictions_cli

    return evaluate_predictions_cli(Path(args.dataset_dir), Path(args.pred_dir), h=args.h,
                                    out_dir=Path(args.out) if args.out else None)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rescu",
        description="RESCU: discover recurring patterns in single photos and use them for 3D "
                    "scene understanding (vanishing points, translation symmetry, counts, "
                    "captions). No configuration file and no Snakemake needed.",
        epilog="Exit codes: 0 ok; 1 some images failed (see their JSON); 2 bad usage, "
               "configuration or input; 3 internal error. The full benchmark pipeline is "
               "`snakemake --cores 2` in the source checkout.")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser(
        "discover", help="find recurring patterns in photos",
        description="Run RESCU on photos (files or folders). Writes, per photo, <stem>.json "
                    "(the per-image result format of the benchmark), <stem>.png (overlay: each "
                    "pattern's instances in its own colour, lines to its vanishing point, the "
                    "caption) and <stem>_rectified/rp<k>.png (rectified views), and prints a "
                    "one-line summary per photo.")
    d.add_argument("photos", nargs="+", metavar="PHOTO",
                   help="image files or folders of images (a folder's images/ subfolder is used "
                        "when present)")
    d.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    d.add_argument("--method", default="rescu-ii", choices=["rescu-ii", "rescu-i", "grasp"],
                   help="rescu-ii (default): stage I extended by the self-supervised stage II; "
                        "rescu-i: stage I only (fast); grasp: the GRASP baseline")
    d.add_argument("--config", metavar="YAML", default=None,
                   help="optional YAML file overriding sections of the default config/config.yaml")
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter, e.g. --set stage1.max_patterns=2 (repeatable)")
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
    e.add_argument("--h", type=float, default=0.5, help="IOD threshold (default 0.5)")
    e.add_argument("--out", metavar="DIR", default=None,
                   help="also write the per-image scores and tables (TSV, Markdown) here")
    e.set_defaults(func=cmd_evaluate)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from .io import InputError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (InputError, ValueError, FileNotFoundError) as e:
        print(f"rescu: error: {e}", file=sys.stderr)
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
