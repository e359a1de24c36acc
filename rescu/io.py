"""File input and output: images, datasets, per-image JSON, HDF5 — all writes atomic.

Every writer here writes to a temporary file in the destination folder and renames it
into place (``os.replace``), so a killed process never leaves a truncated file that a
later step would read as valid.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .types import BBox, ImageResult

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".gif")


_UMASK = os.umask(0)
os.umask(_UMASK)


class InputError(ValueError):
    """Bad input: the message names the file and what is wrong with it."""


class DiskFullError(OSError):
    """No space left (or the disk quota reached) while writing ``filename``: no later
    write can succeed, so a run stops here; files written before are intact (every write
    is atomic)."""

    def __str__(self) -> str:
        return f"{self.filename}: cannot be written: {self.strerror}"


NO_SPACE = {errno.ENOSPC, errno.EDQUOT}
"""``errno`` values of a full disk (:class:`DiskFullError`)."""


# ----------------------------------------------------------------------------- atomic
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On an exception the temporary file is removed and ``path`` is left untouched; a full
    disk raises :class:`DiskFullError` naming ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as e:
        if e.errno in NO_SPACE and not isinstance(e, DiskFullError):
            raise DiskFullError(e.errno, os.strerror(e.errno), str(path)) from None
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def json_text(obj: Any) -> str:
    """``obj`` (an :class:`ImageResult` or plain data with NumPy values) as the JSON text
    :func:`write_json` writes: sorted keys, 1-space indent, deterministic; NaN refused."""
    if isinstance(obj, ImageResult):
        obj = obj.to_json()
    return json.dumps(obj, indent=1, sort_keys=True, default=_jsonable, allow_nan=False)


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as JSON (:func:`json_text`) atomically."""
    text = json_text(obj)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def read_json(path: str | os.PathLike[str]) -> Any:
    """Read a JSON file; a malformed file (or one nested too deeply to read, or not a
    regular file) raises :class:`InputError` naming it."""
    import stat

    path = Path(path)
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            raise InputError(f"{path}: not a regular file")
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be read") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: malformed JSON ({e.msg} at line {e.lineno}, "
                         f"column {e.colno})") from None


def read_result(path: str | os.PathLike[str]) -> ImageResult:
    """Read a per-image result JSON into an :class:`ImageResult`."""
    d = read_json(path)
    pats = d.get("patterns") if isinstance(d, dict) else None
    for i, p in enumerate(pats if isinstance(pats, list) else []):
        insts = p.get("instances") if isinstance(p, dict) else None
        for j, inst in enumerate(insts if isinstance(insts, list) else []):
            problem = box_problem(inst.get("bbox") if isinstance(inst, dict) else None)
            if problem:
                raise InputError(f"{path}: patterns[{i}].instances[{j}].bbox {problem}")
    try:
        return ImageResult.from_json(d)
    except (KeyError, TypeError, ValueError, AttributeError, RecursionError) as e:
        raise InputError(f"{path}: not a per-image result ({type(e).__name__}: "
                         f"{str(e)[:200]})") from None


def box_problem(b: Any) -> str | None:
    """What makes ``b`` not a box ``[x, y, width, height]`` of pixels (four finite
    numbers, width and height >= 0), or None.

    >>> box_problem([1, 2, 3, 4]) is None, box_problem([0, 0, -1, 2])
    (True, 'has a negative width or height: [0, 0, -1, 2]')
    """
    import math

    if (not isinstance(b, (list, tuple)) or len(b) != 4
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in b)):
        return f"must be [x, y, width, height] (four numbers), got {str(b)[:80]}"
    if not all(math.isfinite(v) for v in b):
        return f"is not finite: {list(b)}"
    if b[2] < 0 or b[3] < 0:
        return f"has a negative width or height: {list(b)}"
    return None


def write_h5(path: str | os.PathLike[str], arrays: dict[str, Any],
             attrs: dict[str, Any] | None = None) -> None:
    """Write a flat or nested ``{name: array | dict}`` mapping to HDF5 atomically.

    Nested dicts become groups. ``attrs`` are stored on the root. Datasets are written
    without timestamps so the bytes depend only on the content.
    """
    import h5py

    def put(group: Any, mapping: dict[str, Any]) -> None:
        for k, v in mapping.items():
            if isinstance(v, dict):
                put(group.create_group(k, track_order=True), v)
            else:
                group.create_dataset(k, data=np.asarray(v), track_times=False)

    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            put(f, arrays)
            for k, v in (attrs or {}).items():
                f.attrs[k] = v


def read_h5(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Read an HDF5 file written by :func:`write_h5` into ``(arrays, attrs)``."""
    import h5py

    def get(group: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in group.items():
            out[k] = get(v) if isinstance(v, h5py.Group) else v[()]
        return out

    try:
        with h5py.File(path, "r") as f:
            return get(f), dict(f.attrs)
    except OSError as e:
        raise InputError(f"{path}: unreadable HDF5 file ({e})") from None


def write_image(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB or (H, W) uint8 image as PNG, atomically."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise IOError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


# ----------------------------------------------------------------------------- images
@dataclass
class LoadedImage:
    """A photo ready for processing.

    Attributes
    ----------
    rgb : (H, W, 3) uint8
        Displayed orientation, downscaled so that max(H, W) <= max_side.
    original_size : (int, int)
        ``(width, height)`` of the full-resolution photo in displayed orientation.
    scale_factor : float
        processed = original * scale_factor.
    notes : list of str
        What was done to the input (mode conversion, rotation, downscale).
    """

    rgb: np.ndarray
    original_size: tuple[int, int]
    scale_factor: float
    notes: list[str]


def check_photo_file(path: str | os.PathLike[str]) -> Path:
    """``path`` as a :class:`~pathlib.Path` when it is a regular file (or a link to one).

    Raises :class:`InputError` naming the file and what it is instead: missing, a broken
    symbolic link, a folder, a FIFO, a device or a socket (reading those would block or
    give no image).
    """
    import stat

    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        if path.is_symlink():
            raise InputError(f"{path}: broken symbolic link (points to "
                             f"{os.readlink(path)}, which does not exist)") from None
        raise InputError(f"{path}: file not found") from None
    except OSError as e:
        raise InputError(f"{path}: cannot be read ({e.strerror or e})") from None
    if stat.S_ISREG(mode):
        return path
    kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
    raise InputError(f"{path}: is {kind}, not an image file")


def printable(text: str) -> str:
    r"""``text`` safe to print on a terminal: control characters (escape codes, carriage
    returns, ...) shown as ``\xNN`` / ``\uNNNN`` escapes instead of acted on.

    >>> printable("a\x1b[2Jb.png")
    'a\\x1b[2Jb.png'
    """
    import unicodedata

    return "".join(ch if ch == " " or unicodedata.category(ch)[0] not in "CZ" or ch == "\u3000"
                   else ascii(ch)[1:-1] for ch in str(text))


def display_name(name: str) -> str:
    """``name`` as text that any JSON reader accepts: bytes of a file name that are not
    UTF-8 (kept by Python as lone surrogates) become U+FFFD."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def _orientation(im: Any) -> int:
    """The EXIF orientation tag of an open Pillow image (1 = as stored)."""
    try:
        return int(im.getexif().get(0x0112, 1) or 1)
    except Exception:  # noqa: BLE001  (a broken EXIF block: keep the stored orientation)
        return 1


def _too_large(path: Path, size: str, pixels: int, max_pixels: int) -> str:
    return (f"{path}: image too large ({size}{pixels / 1e6:.1f} megapixels; the limit is "
            f"image.max_pixels = {max_pixels}); downscale it first or raise the limit")


MAX_BYTES_PER_PIXEL = 3
"""A photo's decoded size may be at most ``image.max_pixels`` x this many bytes (8-bit
RGB): a 32-bit or RGBA image is refused over it; a deeper one is decoded and turned into 8 bits
in blocks of rows (no float64 copy of the whole image)."""
_BYTES_PER_PIXEL = {"1": 1, "L": 1, "P": 1, "LA": 2, "PA": 2, "RGB": 3, "YCbCr": 3,
                    "LAB": 3, "HSV": 3, "RGBA": 4, "RGBX": 4, "CMYK": 4, "I;16": 2,
                    "I;16L": 2, "I;16B": 2, "I;16N": 2, "I": 4, "F": 4}


def to_8bit(arr: np.ndarray, rows: int = 512) -> np.ndarray:
    """A grey image of any depth (H, W) as uint8, its largest finite value at 255 and
    everything at or below 0 at 0 (NaN too), converted ``rows`` rows at a time in
    float32 so that no full-size float copy is made.

    >>> to_8bit(np.array([[0, 1000], [2000, 4000]], np.uint16)).tolist()
    [[0, 64], [128, 255]]
    """
    hi = 0.0
    for r in range(0, arr.shape[0], rows):
        block = arr[r:r + rows]
        if block.dtype.kind == "f":
            block = np.where(np.isfinite(block), block, 0)
        if block.size:
            hi = max(hi, float(block.max()))
    scale = np.float32(255.0 / hi) if hi > 0 else np.float32(0.0)
    out = np.empty(arr.shape, np.uint8)
    for r in range(0, arr.shape[0], rows):
        b = arr[r:r + rows].astype(np.float32)
        np.nan_to_num(b, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        b *= scale
        b += np.float32(0.5)
        np.clip(b, 0, 255, out=b)
        out[r:r + rows] = b.astype(np.uint8)
    return out


def load_image(path: str | os.PathLike[str], max_side: int | None = None,
               min_side: int | None = None, max_pixels: int | None = None) -> LoadedImage:
    """Load a photo in displayed orientation as 8-bit RGB, downscaled to ``max_side``.

    Handles grayscale, RGBA (composited on white), 16-bit, palette and EXIF-rotated
    images. Raises :class:`InputError` naming the file for empty, truncated, unreadable
    or non-image files, images smaller than ``min_side`` pixels on a side, and images of
    more than ``max_pixels`` pixels (width x height, read from the file's header before
    anything is decoded, so a huge image costs no memory). ``max_side`` / ``min_side`` /
    ``max_pixels`` default to the configuration's ``image`` section. Pillow's own guard
    (``PIL.Image.MAX_IMAGE_PIXELS``) is left as the caller set it.
    """
    import warnings

    from PIL import Image, ImageOps, UnidentifiedImageError

    from .params import config_defaults

    if max_side is None or min_side is None or max_pixels is None:
        d = config_defaults("image")
        max_side = d["max_side"] if max_side is None else max_side
        min_side = d["min_side"] if min_side is None else min_side
        max_pixels = d["max_pixels"] if max_pixels is None else max_pixels

    path = check_photo_file(path)
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file (0 bytes)")
    notes: list[str] = []
    try:
        with warnings.catch_warnings():
            # our own limit (max_pixels) is checked below; Pillow's warning adds nothing
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im_file = Image.open(path)
        with im_file as im:
            w0, h0 = im.size  # from the header: nothing decoded yet
            if w0 * h0 > max_pixels:
                raise InputError(_too_large(path, f"{w0}x{h0} = ", w0 * h0, max_pixels))
            need = w0 * h0 * _BYTES_PER_PIXEL.get(im.mode, 4)
            if need > max_pixels * MAX_BYTES_PER_PIXEL:
                raise InputError(
                    f"{path}: {w0}x{h0} {im.mode} image decodes to {need / 2**20:.0f} MiB, "
                    f"over the budget of image.max_pixels x {MAX_BYTES_PER_PIXEL} bytes = "
                    f"{max_pixels * MAX_BYTES_PER_PIXEL / 2**20:.0f} MiB; downscale it or "
                    f"convert it to 8 bits first")
            im.load()
            if _orientation(im) != 1:  # exif_transpose copies: only when there is a rotation
                im = ImageOps.exif_transpose(im)
                notes.append("exif-rotated")
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I", "F"):
                arr = np.asarray(im)  # one copy at the file's depth, then Pillow's freed
                im.close()
                im_file.close()
                with warnings.catch_warnings():  # our limits were checked above
                    warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                    im = Image.fromarray(to_8bit(arr), "L")
                del arr
                notes.append(f"{mode}->8bit")
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                im = im.convert("RGBA")
                bg = Image.new("RGBA", im.size, (255, 255, 255, 255))
                im = Image.alpha_composite(bg, im)
                notes.append("alpha-composited")
            if im.mode != "RGB":
                notes.append(f"{im.mode}->RGB")
                im = im.convert("RGB")
            rgb = np.array(im, dtype=np.uint8)
            del im
    except UnidentifiedImageError:
        raise InputError(f"{path}: not an image file (format not recognised)") from None
    except Image.DecompressionBombError as e:  # Pillow's guard refused it at open
        import re

        m = re.search(r"\((\d+) pixels\)", str(e))
        n = int(m.group(1)) if m else 0
        if n > max_pixels:
            raise InputError(_too_large(path, "", n, max_pixels)) from None
        raise InputError(f"{path}: image too large for Pillow's guard, "
                         f"PIL.Image.MAX_IMAGE_PIXELS ({e}); raise that in Python to go "
                         f"up to image.max_pixels = {max_pixels}") from None
    except InputError:
        raise
    except (OSError, SyntaxError, ValueError) as e:
        raise InputError(f"{path}: unreadable or truncated image ({e})") from None
    except MemoryError:
        raise InputError(f"{path}: not enough memory to decode this image; lower "
                         f"image.max_pixels or downscale it first") from None
    return fit_image(rgb, max_side, min_side, str(path), notes)


def fit_image(rgb: np.ndarray, max_side: int, min_side: int, name: str = "image",
              notes: list[str] | None = None) -> LoadedImage:
    """An (H, W, 3) uint8 RGB image ready for processing: refused when a side is below
    ``min_side`` pixels (:class:`InputError` naming ``name``), downscaled (area
    interpolation) so that its longer side is at most ``max_side`` pixels.

    >>> im = fit_image(np.zeros((100, 400, 3), np.uint8), max_side=200, min_side=16)
    >>> im.rgb.shape, im.original_size, im.scale_factor, im.notes
    ((50, 200, 3), (400, 100), 0.5, ['downscaled x0.5000'])
    """
    notes = list(notes or [])
    h, w = rgb.shape[:2]
    if min(h, w) < min_side:
        raise InputError(f"{name}: image too small ({w}x{h} pixels; at least {min_side} "
                         f"pixels per side are needed)")
    scale = 1.0
    if max(h, w) > max_side:
        import cv2

        scale = max_side / float(max(h, w))
        nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
        rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
        scale = nw / float(w)
        notes.append(f"downscaled x{scale:.4f}")
    return LoadedImage(rgb=rgb, original_size=(w, h), scale_factor=scale, notes=notes)


def list_images(folder: str | os.PathLike[str]) -> list[Path]:
    """Image files directly in ``folder`` (sorted by name; other files are ignored)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                  and not p.name.startswith("."))


def skipped_images(folder: str | os.PathLike[str]) -> list[str]:
    """Entries of ``folder`` named like images that :func:`list_images` leaves out, each
    as ``"<name> (<why>)"``: broken symbolic links, folders, FIFOs, devices."""
    out = []
    for p in sorted(Path(folder).iterdir()):
        if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") \
                and not p.is_file():
            try:
                check_photo_file(p)
            except InputError as e:
                out.append(f"{p.name} ({str(e).split(': ', 1)[1]})")
    return out


# ----------------------------------------------------------------------------- datasets
@dataclass
class GroundTruthRP:
    """A ground-truth recurring pattern: the boxes of one category (>= 2) in one image."""

    category: str
    boxes: list[BBox]
    extra: dict[str, Any]


def load_coco_rps(path: str | os.PathLike[str]) -> dict[str, list[GroundTruthRP]]:
    """Ground-truth RPs per image from a COCO ``annotations.json``.

    Returns ``{file_name: [GroundTruthRP, ...]}`` for every image listed (images with no
    RP map to an empty list). Within an image, the boxes of one category with two or
    more boxes form one RP. Raises :class:`InputError` naming the file and field.
    """
    d = read_json(path)
    if not isinstance(d, dict):
        raise InputError(f"{path}: top level must be an object with 'images' and 'annotations'")
    for key in ("images", "annotations"):
        if not isinstance(d.get(key), list):
            raise InputError(f"{path}: field '{key}' missing or not a list")
    cats = {}
    for c in d.get("categories", []) or []:
        if isinstance(c, dict) and isinstance(c.get("id"), (int, str)):
            cats[c["id"]] = str(c.get("name", c["id"]))
    files: dict[Any, str] = {}
    for i, im in enumerate(d["images"]):
        if not isinstance(im, dict) or "id" not in im or "file_name" not in im:
            raise InputError(f"{path}: images[{i}] needs 'id' and 'file_name'")
        if not isinstance(im["id"], (int, str)) or isinstance(im["id"], bool):
            raise InputError(f"{path}: images[{i}].id must be a number or a string")
        name = im["file_name"]
        if not isinstance(name, str) or not name or len(name) > 4096:
            raise InputError(f"{path}: images[{i}].file_name must be a path of 1 to 4096 "
                             f"characters")
        files[im["id"]] = name
    groups: dict[tuple[str, Any], list[tuple[BBox, dict[str, Any]]]] = {}
    for i, a in enumerate(d["annotations"]):
        if not isinstance(a, dict):
            raise InputError(f"{path}: annotations[{i}] is not an object")
        for key in ("image_id", "bbox", "category_id"):
            if key not in a:
                raise InputError(f"{path}: annotations[{i}] has no field '{key}'")
        b = a["bbox"]
        problem = box_problem(b)
        if problem:
            raise InputError(f"{path}: annotations[{i}].bbox {problem}")
        if not isinstance(a["category_id"], (int, str)):
            raise InputError(f"{path}: annotations[{i}].category_id must be a number or a "
                             f"string")
        if not isinstance(a["image_id"], (int, str)) or a["image_id"] not in files:
            raise InputError(f"{path}: annotations[{i}].image_id {repr(a['image_id'])[:80]} "
                             f"is not in 'images'")
        extra = {k: v for k, v in a.items() if k not in ("bbox", "image_id", "id", "area",
                                                          "segmentation", "iscrowd")}
        groups.setdefault((files[a["image_id"]], a["category_id"]), []).append(
            (tuple(float(v) for v in b), extra))  # type: ignore[arg-type]
    out: dict[str, list[GroundTruthRP]] = {f: [] for f in files.values()}
    for (fname, cid), items in sorted(groups.items(), key=lambda kv: (kv[0][0], str(kv[0][1]))):
        if len(items) >= 2:
            out[fname].append(GroundTruthRP(category=cats.get(cid, str(cid)),
                                            boxes=[b for b, _ in items],
                                            extra=items[0][1]))
    return out


def load_vanishing_points(path: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """Ground-truth VPs per image from ``vanishing_points.json``.

    Returns ``{file_name: {"width", "height", "focal_px" (or None), "principal_point"
    (or None), "vanishing_points": [(3,) homogeneous arrays]}}``.
    """
    d = read_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("images"), list):
        raise InputError(f"{path}: field 'images' missing or not a list")
    out: dict[str, dict[str, Any]] = {}
    for i, im in enumerate(d["images"]):
        if not isinstance(im, dict):
            raise InputError(f"{path}: images[{i}] is not an object")
        for key in ("file_name", "width", "height", "vanishing_points"):
            if key not in im:
                raise InputError(f"{path}: images[{i}] has no field '{key}'")
        for key in ("width", "height"):
            v = im[key]
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v < 1e6:
                raise InputError(f"{path}: images[{i}].{key} must be a number of pixels > 0, "
                                 f"got {str(v)[:40]!r}")
        if not isinstance(im["vanishing_points"], list):
            raise InputError(f"{path}: images[{i}].vanishing_points must be a list")
        vps = []
        for j, vp in enumerate(im["vanishing_points"]):
            h = vp.get("homogeneous") if isinstance(vp, dict) else None
            if (not isinstance(h, list) or len(h) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                               and np.isfinite(v) for v in h)):
                raise InputError(f"{path}: images[{i}].vanishing_points[{j}].homogeneous "
                                 f"must be [x, y, w], three finite numbers")
            vps.append(np.asarray(h, float))
        out[str(im["file_name"])] = {
            "width": int(im["width"]), "height": int(im["height"]),
            "focal_px": im.get("focal_px"), "principal_point": im.get("principal_point"),
            "vanishing_points": vps, "extra": {k: v for k, v in im.items()
                                               if k not in ("vanishing_points",)},
        }
    return out
