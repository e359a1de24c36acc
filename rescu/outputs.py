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
* **No link is followed.** A result file, ``rescu.log``, ``index.html``, the staging
  area ``.rescu-work`` or the ``--keep-work`` folder ``.work/<name>`` that is a symbolic
  link is refused (:func:`check_path`), never written through nor swept.
* **Runs on one folder take turns.** The manifest's read-change-write and the gallery
  happen under one lock (``fcntl.flock`` on ``.rescu-lock``, :func:`locked`), so two
  runs writing into one folder both keep their results.

The folder's own files ``rescu.log`` and ``index.html`` are recorded in the manifest too
(``"own"``): a ``rescu.log`` or ``index.html`` of the user's is refused like a result.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import stat
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
LOCK = ".rescu-lock"
"""The lock file the runs writing into one output folder take turns on (:func:`locked`)."""
LOG = "rescu.log"
GALLERY = "index.html"
OWN = (LOG, GALLERY)
"""The output folder's files of rescu's own beside the result sets (manifest ``"own"``)."""
OPEN = "open"
"""The manifest's mark of an own file being written (the log during a run)."""
EARLIER = "earlier"
"""The mark given, on reading, to the own files of a manifest without ``"own"``: an
earlier rescu wrote ``rescu.log`` and ``index.html`` there without recording them."""


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
    if not _lexists(path):
        return {"format": 1, "results": {}, "own": {}}
    check_path(path, "rescu's manifest")
    if not stat.S_ISREG(os.lstat(path).st_mode):
        raise InputError(f"{path}: not a regular file (rescu's manifest of results); move it "
                         f"away or choose another output folder")
    d = read_json(path)
    bad = _manifest_problem(d)
    if bad:
        raise InputError(f"{path}: not rescu's manifest of results ({bad}); move it away or "
                         f"choose another output folder")
    if "own" not in d:  # written before rescu recorded its log and page: they are its own
        d["own"] = {rel: [EARLIER] for rel in OWN}
    return d


def _manifest_problem(d: Any) -> str | None:
    """What makes ``d`` not a manifest (None: it is one)."""
    if not isinstance(d, dict) or not isinstance(d.get("results"), dict):
        return "no 'results' mapping"
    for name, entry in d["results"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("files", {}), dict):
            return f"results.{name}: not a mapping with a 'files' mapping"
        for rel, hashes in (entry.get("files") or {}).items():
            if not (isinstance(hashes, list) and all(isinstance(h, str) for h in hashes)):
                return f"results.{name}.files.{rel}: not a list of hashes"
    own = d.get("own", {})
    if not isinstance(own, dict) or not all(
            isinstance(v, list) and all(isinstance(h, str) for h in v) for v in own.values()):
        return "'own': not a mapping of lists of hashes"
    return None


def _lexists(path: Path) -> bool:
    try:
        os.lstat(path)
    except FileNotFoundError:
        return False
    return True


def check_path(path: str | os.PathLike[str], what: str = "a file rescu writes") -> Path:
    """``path`` when it is not a symbolic link (it may not exist); :class:`InputError`
    naming it otherwise. rescu never writes through, sweeps or reads its own files
    through a link in an output folder."""
    path = Path(path)
    if path.is_symlink():
        raise InputError(f"{path}: is a symbolic link ({what}); rescu does not follow links "
                         f"in its output folder: remove the link or choose another folder")
    return path


def safe_dir(out_dir: str | os.PathLike[str], rel: str) -> Path:
    """``out_dir/rel`` created folder by folder, none of its parts below ``out_dir`` a
    link (:class:`InputError` naming the link) nor a file."""
    cur = Path(out_dir)
    for part in Path(rel).parts:
        cur = check_path(cur / part, "a folder rescu writes into")
        for _ in range(20):
            try:
                cur.mkdir()
                break
            except FileExistsError:
                try:
                    mode = os.lstat(cur).st_mode
                except FileNotFoundError:  # another run removed it meanwhile: make it again
                    continue
                if not stat.S_ISDIR(mode):
                    raise InputError(f"{cur}: exists and is not a folder") from None
                break
    return cur


@contextlib.contextmanager
def locked(out_dir: str | os.PathLike[str]) -> Iterator[None]:
    """Hold the output folder's lock (``.rescu-lock``, ``fcntl.flock``, exclusive): runs
    writing into one folder change its manifest and gallery in turn."""
    import fcntl

    path = check_path(Path(out_dir) / LOCK, "rescu's lock")
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as e:
        raise InputError(f"{path}: cannot open rescu's lock ({e.strerror or e})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(f"{path}: not a regular file (rescu's lock)")
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


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


def foreign_own(out_dir: str | os.PathLike[str], manifest: dict[str, Any] | None = None
                ) -> list[Path]:
    """``rescu.log`` and ``index.html`` of ``out_dir`` when they exist and rescu did not
    write them (a link, or not in the manifest's ``"own"`` with their content; a log
    marked :data:`OPEN` was being written by a run, perhaps killed: rescu's)."""
    out = Path(out_dir)
    own = (read_manifest(out) if manifest is None else manifest).get("own", {})
    found = []
    for rel in OWN:
        p = out / rel
        if not _lexists(p):
            continue
        hashes = own.get(rel) or []
        if p.is_symlink() or not p.is_file() or not (
                (rel == LOG and OPEN in hashes) or EARLIER in hashes
                or _sha256(p) in hashes):
            found.append(p)
    return found


def check_targets(out_dir: str | os.PathLike[str], names: Sequence[str],
                  force: bool = False, own: bool = True) -> None:
    """Refuse, before any work, result sets that would replace files rescu did not write.

    Parameters
    ----------
    out_dir : path
        The output folder (may not exist yet).
    names : sequence of str
        The result names (``<name>.json``, ...) of the photos to run.
    force : bool
        Replace such files anyway (``rescu discover --force``); a link is never
        written through, forced or not.
    own : bool
        Also check the folder's ``rescu.log`` and ``index.html`` (the command line
        writes them; :func:`rescu.discover` does not).

    Raises
    ------
    OverwriteError
        Naming the first few such files and how to proceed.
    """
    out = Path(out_dir)
    for n in names:
        check_name(n)
    if not out.is_dir():
        return
    for rel in (MANIFEST, LOCK, WORK) + (OWN if own else ()):  # forced or not
        check_path(out / rel, "rescu's own file or folder")
    if force:
        return
    manifest = read_manifest(out)
    found = (foreign_own(out, manifest) if own else []) + [p for n in names
                                          for p in foreign_files(out, n, manifest)]
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
    (a killed run's); return them. A link (``.rescu-work`` or an entry) is never
    followed: a linked ``.rescu-work`` is refused (:func:`check_path`), a linked entry
    left alone."""
    work = check_path(Path(out_dir) / WORK, "rescu's staging area")
    removed = []
    if work.is_dir():
        for p in sorted(work.iterdir()):
            pid = p.name.split("-", 1)[0]
            if (pid.isdigit() and int(pid) != os.getpid() and not p.is_symlink()
                    and p.is_dir() and not _alive(int(pid))):
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
    is None. A ``.rescu-work`` that is a link is refused; one that another run removes
    (it was empty) while this one makes its folder is made again.
    """
    if out_dir is None:
        path = Path(tempfile.mkdtemp(prefix=f"rescu-{os.getpid()}-"))
    else:
        for attempt in range(20):
            try:
                base = safe_dir(out_dir, WORK)
                path = Path(tempfile.mkdtemp(prefix=f"{os.getpid()}-", dir=base))
                break
            except FileNotFoundError:  # another run's rmdir of the empty area
                if attempt == 19:
                    raise
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
    with locked(out_dir):
        _commit(Path(out_dir), name, staged, image)


def _commit(out: Path, name: str, staged: Path, image: str) -> None:
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


def record_own(out_dir: str | os.PathLike[str], rel: str, value: str | None = None) -> None:
    """Record the own file ``rel`` (:data:`OWN`) of ``out_dir`` as rescu's in the manifest:
    its current SHA-256, or ``value`` (:data:`OPEN` while the log is written). The
    caller holds :func:`locked`."""
    out = Path(out_dir)
    manifest = read_manifest(out)
    p = check_path(out / rel)
    manifest["own"][rel] = [value if value is not None else _sha256(p)]
    write_json(out / MANIFEST, manifest)


def open_log(out_dir: str | os.PathLike[str]) -> Any:
    """``out_dir/rescu.log`` opened for this run's messages (a text stream; the caller
    closes it), never through a link (``O_NOFOLLOW``) and recorded as rescu's
    (:data:`OPEN`). Appended to while another run writes it (both hold a shared
    ``flock`` on it), emptied first otherwise. The caller checked it is not a user's
    (:func:`check_targets`)."""
    import fcntl

    path = check_path(Path(out_dir) / LOG, "rescu's log")
    with locked(out_dir):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW
                         | os.O_CLOEXEC, 0o666 & ~_umask())
        except OSError as e:
            raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise InputError(f"{path}: not a regular file (rescu's log)")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.ftruncate(fd, 0)      # nobody else writes it: a fresh log
        except BlockingIOError:
            pass                     # another run writes it: append
        fcntl.flock(fd, fcntl.LOCK_SH)
        record_own(out_dir, LOG, OPEN)
    return os.fdopen(fd, "a", encoding="utf-8")


def close_log(out_dir: str | os.PathLike[str], stream: Any) -> None:
    """Close the log of :func:`open_log` and record its content as rescu's."""
    stream.close()
    with contextlib.suppress(OSError):  # a full disk: the log stays marked open (rescu's)
        with locked(out_dir):
            if (Path(out_dir) / LOG).is_file():
                record_own(out_dir, LOG)


def names_in(out_dir: str | os.PathLike[str], first: Sequence[str] = ()) -> list[str]:
    """The result names of ``out_dir``'s manifest, ``first`` (this run's, those
    recorded) in their order, then the others sorted."""
    recorded = read_manifest(out_dir)["results"]
    return ([n for n in first if n in recorded]
            + sorted(n for n in recorded if n not in set(first)))


def _umask() -> int:
    from .io import _UMASK

    return _UMASK
