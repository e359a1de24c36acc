"""A photo's result set in a user's output folder: what may be replaced, and how.

``rescu discover`` (and :func:`rescu.discover` with ``out_dir``) writes, per photo, the
*result set* ``<name>.json``, ``<name>.png`` and ``<name>_rectified/rp<k>.png`` into a
folder the user owns. Two rules keep that safe:

* **Nothing rescu did not write is replaced.** Every file of a result set is recorded,
  with its SHA-256, in the folder's manifest (``.rescu-results.json``). A target that
  exists and is not recorded with its current content (a photo, someone's notes, a
  result edited since) is refused before any work (:func:`check_targets`), unless the
  caller forces it.
* **A rerun replaces the whole set.** The new files are made in a staging folder inside
  the output folder (``.rescu-work/<pid>-<random>/``, :func:`staging`) and moved into
  place together (:func:`commit`): stale rectified views of an earlier run (``rp5.png``
  when the new run found 3 RPs) go, and a killed run leaves the previous set as it was.
  Staging folders of processes that no longer run are removed by the next run
  (:func:`sweep_stale_work`).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator, Sequence

from .io import InputError, read_json, write_json

MANIFEST = ".rescu-results.json"
"""The manifest of an output folder: ``{"format": 1, "results": {name: {"image": str,
"files": {relative path: [sha256, ...]}}}}`` (a list: while a set is being replaced
both the old and the new content count as rescu's)."""
WORK = ".rescu-work"
"""The output folder's staging area (one sub-folder per running process)."""


class OverwriteError(InputError):
    """A result would replace a file that rescu did not write (message names it)."""


def check_name(name: str) -> str:
    """``name`` when it is a plain file name that keeps the results inside the output
    folder; :class:`InputError` otherwise (``../x``, ``a/b``, ``..``, empty, reserved)."""
    if (not isinstance(name, str) or not name or name in (".", "..") or "\0" in name
            or os.sep in name or (os.altsep and os.altsep in name)):
        raise InputError(f"name {name!r}: must be a plain file name (no folder part); "
                         f"results are written only inside out_dir")
    if name in (Path(MANIFEST).stem, WORK, ".work"):
        raise InputError(f"name {name!r}: reserved for rescu's own files in out_dir")
    return name


def result_files(name: str) -> tuple[str, str, str]:
    """The relative paths of a result set: ``(<name>.json, <name>.png, <name>_rectified)``."""
    return f"{name}.json", f"{name}.png", f"{name}_rectified"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_manifest(out_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of ``out_dir`` (an empty one when there is none).

    Raises :class:`InputError` naming the file when it exists but is not a manifest.
    """
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        return {"format": 1, "results": {}}
    d = read_json(path)
    if not (isinstance(d, dict) and isinstance(d.get("results"), dict)):
        raise InputError(f"{path}: not rescu's manifest of results (no 'results' mapping); "
                         f"move it away or choose another output folder")
    return d


def _recorded(manifest: dict[str, Any]) -> dict[str, list[str]]:
    """``{relative path: [accepted sha256, ...]}`` over every result set of a manifest."""
    out: dict[str, list[str]] = {}
    for entry in manifest["results"].values():
        for rel, hashes in (entry.get("files") or {}).items() if isinstance(entry, dict) else ():
            out.setdefault(rel, []).extend(hashes if isinstance(hashes, list) else [hashes])
    return out


def foreign_files(out_dir: str | os.PathLike[str], name: str,
                  manifest: dict[str, Any] | None = None) -> list[Path]:
    """The existing targets of ``name``'s result set in ``out_dir`` that rescu did not
    write (not in the manifest with their current content): what a run would replace."""
    out = Path(out_dir)
    recorded = _recorded(read_manifest(out) if manifest is None else manifest)

    def ours(rel: str) -> bool:
        p = out / rel
        return not p.is_symlink() and p.is_file() and _sha256(p) in recorded.get(rel, ())

    found: list[Path] = []
    json_rel, png_rel, rect_rel = result_files(name)
    for rel in (json_rel, png_rel):
        p = out / rel
        if (p.exists() or p.is_symlink()) and not ours(rel):
            found.append(p)
    rect = out / rect_rel
    if rect.is_symlink() or (rect.exists() and not rect.is_dir()):
        found.append(rect)
    elif rect.is_dir():
        found += [p for p in sorted(rect.rglob("*"))
                  if not p.is_dir() and not ours(str(p.relative_to(out)))]
    return found


def check_targets(out_dir: str | os.PathLike[str], names: Sequence[str],
                  force: bool = False) -> None:
    """Refuse, before any work, result sets that would replace files rescu did not write.

    Parameters
    ----------
    out_dir : path
        The output folder (may not exist yet).
    names : sequence of str
        The result names (``<name>.json``, ...) of the photos to run.
    force : bool
        Replace such files anyway (``rescu discover --force``).

    Raises
    ------
    OverwriteError
        Naming the first few such files and how to proceed.
    """
    out = Path(out_dir)
    for n in names:
        check_name(n)
    if force or not out.is_dir():
        return
    manifest = read_manifest(out)
    found = [p for n in names for p in foreign_files(out, n, manifest)]
    if found:
        shown = ", ".join(str(p) for p in found[:3]) + (f" and {len(found) - 3} more"
                                                         if len(found) > 3 else "")
        raise OverwriteError(f"{shown}: not written by rescu (or changed since), and the "
                             f"results would replace {'it' if len(found) == 1 else 'them'}; "
                             f"choose another output folder, move the file(s) away, or "
                             f"pass --force (force=True) to replace them")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale_work(out_dir: str | os.PathLike[str]) -> list[Path]:
    """Remove the staging folders in ``out_dir/.rescu-work`` whose process no longer runs
    (a killed run's); return them."""
    work = Path(out_dir) / WORK
    removed = []
    if work.is_dir():
        for p in sorted(work.iterdir()):
            pid = p.name.split("-", 1)[0]
            if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p)
        with contextlib.suppress(OSError):
            work.rmdir()  # only when empty
    return removed


@contextlib.contextmanager
def staging(out_dir: str | os.PathLike[str] | None) -> Iterator[Path]:
    """A fresh folder for one photo's work and new result set, removed on exit.

    In ``out_dir/.rescu-work/<pid>-<random>/`` (same file system as the results, so
    :func:`commit` only renames), or in the system's temporary folder when ``out_dir``
    is None.
    """
    if out_dir is None:
        path = Path(tempfile.mkdtemp(prefix=f"rescu-{os.getpid()}-"))
    else:
        base = Path(out_dir) / WORK
        base.mkdir(parents=True, exist_ok=True)
        path = Path(tempfile.mkdtemp(prefix=f"{os.getpid()}-", dir=base))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
        if out_dir is not None:
            with contextlib.suppress(OSError):
                (Path(out_dir) / WORK).rmdir()  # only when empty


def _set_files(out: Path, name: str, root: Path) -> dict[str, list[str]]:
    """``{path relative to out: [sha256]}`` of the result set ``name`` lying under
    ``root`` (the staging folder, laid out like ``out``)."""
    files = {}
    for rel in result_files(name):
        p = root / rel
        if p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file():
                    files[f"{rel}/{q.relative_to(p)}"] = [_sha256(q)]
        elif p.is_file():
            files[rel] = [_sha256(p)]
    return files


def commit(out_dir: str | os.PathLike[str], name: str, staged: Path, image: str) -> None:
    """Move the result set ``name`` made under ``staged`` into ``out_dir``, replacing the
    previous set of that name as a whole, and record it in the manifest.

    The manifest first accepts both the old and the new files, then the files are
    renamed (rectified views, overlay, JSON last), then the manifest keeps the new
    ones only: a kill at any point leaves files that a rerun recognises as its own.
    """
    out = Path(out_dir)
    manifest = read_manifest(out)
    new = _set_files(out, name, staged)
    old = (manifest["results"].get(name) or {}).get("files") or {}
    both = {rel: list(dict.fromkeys((old.get(rel) or []) + (new.get(rel) or [])))
            for rel in {**old, **new}}
    manifest["results"][name] = {"image": image, "files": both}
    write_json(out / MANIFEST, manifest)
    json_rel, png_rel, rect_rel = result_files(name)
    rect, new_rect = out / rect_rel, staged / rect_rel
    if rect.is_dir() and not rect.is_symlink():
        rect.rename(staged / f"{rect_rel}.old")  # removed with the staging folder
    elif rect.exists() or rect.is_symlink():
        rect.unlink()  # only reached with force
    if new_rect.is_dir() and any(new_rect.iterdir()):
        new_rect.rename(rect)
    for rel in (png_rel, json_rel):
        if (staged / rel).is_file():
            os.replace(staged / rel, out / rel)
        elif (out / rel).is_file() or (out / rel).is_symlink():
            (out / rel).unlink()
    manifest["results"][name] = {"image": image, "files": new}
    write_json(out / MANIFEST, manifest)
