"""Run the pipeline's per-image steps in processes forked from one that has already
imported their libraries: a *step server*.

Each per-image job of the workflow is a new Python process (``workflow/run_step.py``),
and before it does any work it imports its libraries: NumPy, OpenCV, SciPy and h5py
(0.2-0.6 s), and for the steps that run the backbone (``dense``, ``stage2_features``,
``stage2_ablation``) torch as well (about 2 s with torch's CUDA build, less with its CPU
wheels). Over an image's seven or so jobs that is about a fifth of what a run of the
real sets costs (``benchmarks/speed/job_overhead.py``,
``benchmarks/speed/step_imports.py``).

With the server the job's command is ``python -m rescu_workflow.step_server --idle=SECONDS
workflow/run_step.py SCRIPT JOB LOG`` (:func:`main`; ``step_params`` in
``workflow/rules/common.smk`` writes it when ``step_server.enabled``), and the job's
process is a small *client* that imports nothing but the standard library: it connects
to a Unix socket, where a server that imported those libraries once (:data:`PRELOAD`,
never ``rescu`` itself, so that every step runs the checkout's code as it is) forks a child for the job. The child takes the client's
standard input, output and error (passed over the socket), its working directory,
environment, ``sys.argv`` and ``sys.path``, runs the step as the client would have, and
sends back its exit status, which the client exits with. What the step computes is the
same code on the same data, so its outputs are the same (``tests/test_step_server.py``;
the runs of ``docs/results.md``). The first client starts the server (under a lock, so
that concurrent jobs start one); it exits after ``idle_s`` seconds without a job.

Safety:

* Only this user's processes meet at the socket. Socket and lock live in a folder of
  this user's that nobody else may enter (:func:`private_dir`: ``rescu-steps-<uid>``
  under ``$XDG_RUNTIME_DIR`` or the temporary directory, mode 0700, checked not to be a
  link nor someone else's, :func:`ensure_private`); both ends check the other's user id
  (``SO_PEERCRED``): the server serves no other user's client, the client sends its
  environment and streams to no other user's server; the lock is opened without
  following links. Where any of it fails, the client says why on its standard error and
  the step runs in its own process.
* A signal the client gets (Snakemake cancelling the job) is passed on to the child; a
  child whose client has gone (killed) kills itself, so no step outlives its job.
* A child that dies without a status (a crash, the kernel's OOM killer) makes the client
  exit with 1 and a message on its standard error.
* The server is keyed by the Python, ``sys.path`` and the environment variables that
  libraries read when they are loaded (:data:`ENV_KEYS`: thread counts and library
  paths): a job whose fresh process would have loaded them otherwise gets a server of
  its own.
* Where the server cannot be used (not Linux, no ``socket.send_fds``, inside a SLURM job,
  whose processes the cluster ends with the job, or the server fails to start) the step
  runs in the client's own process as before: :func:`run_via_server` returns None.

What changes for measurements: Snakemake's ``benchmark:`` files time the job as before
(``s``), but their memory and CPU columns are the client's. Memory per step is measured
without the server (``step_server.enabled: false`` in the configuration) or with
``benchmarks/speed/step_memory.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import stat
import struct
import sys
import tempfile
import time
from typing import Any, Callable, Sequence

PRELOAD: tuple[str, ...] = ("numpy", "cv2", "h5py", "yaml", "scipy.spatial",
                            "scipy.special", "torch", "efficientnet_lite_pytorch")
"""Modules the server imports before it serves (those it cannot import are skipped)."""

ENV_KEYS: tuple[str, ...] = (
    "PYTHONPATH", "PYTHONHASHSEED", "LD_LIBRARY_PATH", "LD_PRELOAD", "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "GOTO_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS", "MALLOC_ARENA_MAX", "CUDA_VISIBLE_DEVICES")
"""Environment variables libraries read when they load: a server per set of values."""

_PROTOCOL = 1
_HEADER = struct.Struct("!I")       # length of the request's JSON
_STATUS = struct.Struct("!i")       # the child's pid, then its exit status
_CREDS = struct.Struct("3i")        # SO_PEERCRED: pid, uid, gid
_MAX_UNIX_PATH = 107                # bytes of a Unix socket's path (sun_path, NUL excluded)
_START_TIMEOUT_S = 120.0            # the server's imports: a few seconds, more on a busy machine


def available() -> bool:
    """Whether steps can run through a server here: Linux with ``socket.send_fds``
    (Python 3.9+) and ``os.fork``, outside a SLURM job."""
    return (sys.platform.startswith("linux") and hasattr(socket, "send_fds")
            and hasattr(os, "fork") and "SLURM_JOB_ID" not in os.environ)


def socket_path(directory: str | None = None, env: dict[str, str] | None = None,
                path: Sequence[str] | None = None) -> str:
    """The server's socket for this Python, ``sys.path`` and :data:`ENV_KEYS` values
    (``env``: ``os.environ``; ``path``: ``sys.path``), in this user's private folder
    under ``directory`` (:func:`private_dir`; default base: :func:`default_base`)."""
    env = os.environ if env is None else env
    key = json.dumps([_PROTOCOL, sys.executable, list(sys.path if path is None else path),
                      {k: env.get(k) for k in ENV_KEYS}, PRELOAD])
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return os.path.join(private_dir(directory), f"{digest}.sock")


def default_base() -> str:
    """Where the private folder goes: ``$XDG_RUNTIME_DIR`` when it is a folder of this
    user's that nobody else may enter (the login's runtime folder), else the temporary
    directory."""
    run = os.environ.get("XDG_RUNTIME_DIR")
    if run:
        try:
            st = os.lstat(run)
        except OSError:
            st = None
        if (st is not None and stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid()
                and not st.st_mode & 0o077):
            return run
    return tempfile.gettempdir()


def private_dir(directory: str | None = None) -> str:
    """This user's folder for the server's socket and lock: ``<base>/rescu-steps-<uid>``
    (``directory``, default :func:`default_base`). Nothing is created here
    (:func:`ensure_private` does)."""
    return os.path.join(directory or default_base(), f"rescu-steps-{os.getuid()}")


class UnsafeError(OSError):
    """The socket's folder, the lock or the peer at the other end of the socket is not
    this user's alone (the message says which and why)."""


def ensure_private(folder: str) -> None:
    """Create ``folder`` with mode 0700 when missing; raise :class:`UnsafeError` unless
    it is a real folder (not a link) owned by this user that nobody else may enter."""
    try:
        os.mkdir(folder, 0o700)
    except FileExistsError:
        pass
    st = os.lstat(folder)
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise UnsafeError(f"{folder} is not a folder (a link or a file)")
    if st.st_uid != os.getuid():
        raise UnsafeError(f"{folder} belongs to uid {st.st_uid}, not to this user "
                          f"({os.getuid()})")
    if st.st_mode & 0o077:
        raise UnsafeError(f"{folder} may be entered by others (mode "
                          f"{stat.S_IMODE(st.st_mode):04o}, must be 0700); remove it")


def peer_uid(conn: socket.socket) -> int:
    """The user id of the process at the other end of a Unix socket (``SO_PEERCRED``)."""
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _CREDS.size)
    return _CREDS.unpack(creds)[1]


def _check_peer(conn: socket.socket, what: str) -> None:
    uid = peer_uid(conn)
    if uid != os.getuid():
        raise UnsafeError(f"the {what} at the other end of the socket is uid {uid}, not "
                          f"this user ({os.getuid()})")


def _refuse(reason: object) -> None:
    """Say once, on standard error, why the step runs without the server."""
    sys.stderr.write(f"rescu step server: not used ({reason}); the step runs in its own "
                     f"process\n")


# ------------------------------------------------------------------------------ client
def run_via_server(argv: Sequence[str], runner: str, idle_s: float = 30.0,
                   directory: str | None = None) -> int | None:
    """Run a job in a child of the step server, starting the server when none is running.

    Parameters
    ----------
    argv : the job's arguments (``workflow/run_step.py``'s ``SCRIPT JOB [LOG ...]``)
    runner : path of the Python file the child runs as ``python runner *argv`` would
        (``workflow/run_step.py``)
    idle_s : a server started here ends after this many seconds without a job
    directory : where the socket lives (default: the temporary directory)

    Returns
    -------
    The child's exit status, or None when no server could be used (nothing was run: the
    caller runs the job itself).
    """
    if not available():
        return None
    path = socket_path(directory)
    if len(os.fsencode(path)) + 12 > _MAX_UNIX_PATH:   # + the server's ".<pid>.tmp"
        _refuse(f"the socket's path {path} is too long for a Unix socket")
        return None
    for attempt in range(2):                # a server that was just ending: start another
        try:
            ensure_private(os.path.dirname(path))
            conn = _connect(path) or _start(path, idle_s)
        except UnsafeError as e:
            _refuse(e)
            return None
        except OSError:
            return None
        if conn is None:
            return None
        try:
            return _run(conn, argv, os.path.abspath(runner))
        except _NotStarted:
            conn.close()
            continue
    return None


class _NotStarted(Exception):
    """The server closed the connection before it started the job."""


def _connect(path: str) -> socket.socket | None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(path)
    except OSError:
        s.close()
        return None
    try:
        _check_peer(s, "server")             # a socket planted by someone else
    except BaseException:
        s.close()
        raise
    return s


def _start(path: str, idle_s: float) -> socket.socket | None:
    """Start a server on ``path`` (under a lock: one per path) and connect to it."""
    import fcntl
    import subprocess

    try:                                     # never through a planted link
        fd = os.open(path + ".lock", os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC,
                     0o600)
    except OSError as e:
        raise UnsafeError(f"cannot open the lock {path}.lock without following links "
                          f"({e.strerror or e})") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid():
        os.close(fd)
        raise UnsafeError(f"the lock {path}.lock is not a file of this user's")
    with os.fdopen(fd, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        conn = _connect(path)                # another job started it meanwhile
        if conn is not None:
            return conn
        try:
            os.unlink(path)                  # a server that ended without removing it
        except FileNotFoundError:
            pass
        boot = ("import sys, json; sys.path[:] = json.loads(sys.argv[1]); "
                "from rescu_workflow.step_server import serve; "
                "serve(sys.argv[2], float(sys.argv[3]))")
        proc = subprocess.Popen(
            [sys.executable, "-c", boot, json.dumps(sys.path), path, repr(float(idle_s))],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            close_fds=True, start_new_session=True)
        end = time.monotonic() + _START_TIMEOUT_S
        while time.monotonic() < end and proc.poll() is None:
            conn = _connect(path)
            if conn is not None:
                return conn
            time.sleep(0.02)
        return None


def _recv_exact(s: socket.socket, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


def _run(conn: socket.socket, argv: Sequence[str], runner: str) -> int:
    request = json.dumps({"argv": list(argv), "runner": runner, "cwd": os.getcwd(),
                          "env": dict(os.environ), "path": list(sys.path)}).encode()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    try:
        socket.send_fds(conn, [_HEADER.pack(len(request)) + request], [0, 1, 2])
        head = _recv_exact(conn, _STATUS.size)
    except OSError as e:
        raise _NotStarted() from e
    if head is None:
        raise _NotStarted()
    (pid,) = _STATUS.unpack(head)

    def forward(signum: int, frame: Any) -> None:
        try:
            os.kill(pid, signum)
        except ProcessLookupError:
            pass

    signals = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)
    before = [signal.signal(sig, forward) for sig in signals]
    try:
        tail = _recv_exact(conn, _STATUS.size)
    except OSError:
        tail = None
    finally:
        conn.close()
        for sig, handler in zip(signals, before):
            signal.signal(sig, handler)
    if tail is None:
        sys.stderr.write("rescu step server: the step's process ended without an exit "
                         "status (killed by a signal, or out of memory)\n")
        return 1
    return _STATUS.unpack(tail)[0]


# ------------------------------------------------------------------------------ server
def serve(path: str, idle_s: float = 30.0, preload: Sequence[str] = PRELOAD,
          runner: Callable[[Sequence[str]], None] | None = None) -> None:
    """The step server: import ``preload``, listen on ``path`` and fork a child per
    connection, until ``idle_s`` seconds pass without one; then remove ``path``.

    ``runner``: runs a job's ``argv`` in the child (default: the file the client names,
    ``workflow/run_step.py``, run as ``python runner *argv`` would run it).
    """
    import importlib

    for name in preload:
        try:
            importlib.import_module(name)
        except Exception:                    # noqa: BLE001 - a missing library: the
            pass                             # step imports it (or fails) itself
    # every job imports rescu from the checkout as it is now, not as it was at the start
    for name in [m for m in sys.modules if m == "rescu" or m.startswith("rescu.")]:
        if name != __name__:
            del sys.modules[name]
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)      # children reaped by the kernel
    tmp = f"{path}.{os.getpid()}.tmp"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(tmp)
    os.chmod(tmp, 0o600)                    # the folder is 0700 too
    srv.listen(64)
    os.replace(tmp, path)                   # ready: clients connect from here on
    srv.settimeout(idle_s)
    try:
        while True:
            try:
                conn, _ = srv.accept()
            except socket.timeout:
                break
            _fork_job(srv, conn, runner)
        # no job for idle_s: leave, serving the connections already queued
        try:
            os.unlink(path)
        except OSError:
            pass
        srv.setblocking(False)
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:                  # none queued (BlockingIOError) or closed
                break
            conn.setblocking(True)
            _fork_job(srv, conn, runner)
    finally:
        srv.close()


def _fork_job(srv: socket.socket, conn: socket.socket,
              runner: Callable[[Sequence[str]], None] | None) -> None:
    try:
        _check_peer(conn, "client")          # only this user's jobs run as this user
    except OSError:
        conn.close()
        return
    try:
        msg, fds, _, _ = socket.recv_fds(conn, 1 << 16, 3)
    except OSError:
        conn.close()
        return
    if len(fds) != 3 or len(msg) < _HEADER.size:
        for fd in fds:
            os.close(fd)
        conn.close()
        return
    (n,) = _HEADER.unpack(msg[:_HEADER.size])
    body = msg[_HEADER.size:]
    if len(body) < n:
        rest = _recv_exact(conn, n - len(body))
        body = body + (rest or b"")
    pid = os.fork()
    if pid:
        for fd in fds:
            os.close(fd)
        conn.close()
        return
    # the child: the job
    status = 1
    try:
        conn.sendall(_STATUS.pack(os.getpid()))  # first: the client signals this pid
        _watch(conn)
        srv.close()
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        os.setsid()                          # its own group: signals reach it alone
        request = json.loads(body)
        for target, fd in zip((0, 1, 2), fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        sys.path[:] = request["path"]
        status = _run_job(request["argv"], runner or request["runner"])
    except BaseException:                    # noqa: BLE001 - reported, then the status
        import traceback

        traceback.print_exc()
        status = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:                # noqa: BLE001
                pass
        try:
            conn.sendall(_STATUS.pack(status))
        finally:
            os._exit(status)


def _run_job(argv: Sequence[str], runner: Callable[[Sequence[str]], None] | str) -> int:
    """Run the job, its exit status as a fresh process's would be: ``runner`` is a
    function of ``argv``, or the path of a Python file run as ``python runner *argv``
    would run it (:func:`run_file`)."""
    if isinstance(runner, str):
        runner = _file_runner(runner)
    try:
        runner(list(argv))
    except SystemExit as e:
        if e.code is None:
            return 0
        if isinstance(e.code, int):
            return e.code
        print(e.code, file=sys.stderr)
        return 1
    return 0


def _file_runner(path: str) -> Callable[[Sequence[str]], None]:
    def run(argv: Sequence[str]) -> None:
        run_file(path, argv)
    return run


def run_file(path: str, argv: Sequence[str]) -> None:
    """Run the Python file ``path`` as ``python path *argv`` would: as ``__main__``, with
    ``sys.argv`` ``[path, *argv]`` and its own folder first on ``sys.path``."""
    import runpy

    path = os.path.abspath(path)
    sys.argv = [path, *argv]
    sys.path[0:1] = [os.path.dirname(path)]
    runpy.run_path(path, run_name="__main__")


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m rescu_workflow.step_server [--idle=SECONDS] RUNNER ARG ...``: run
    ``python RUNNER ARG ...`` in a child of the step server (started when none runs; it ends after
    ``SECONDS`` idle, default 30), or in this process where no server can be used; exit
    with its status. The pipeline's per-image jobs run so with ``step_server.enabled``
    (``RUNNER`` = ``workflow/run_step.py``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    idle_s = 30.0
    if args and args[0].startswith("--idle="):
        value, args = args[0].split("=", 1)[1], args[1:]
        try:
            idle_s = float(value)
        except ValueError:
            idle_s = float("nan")
        if not idle_s > 0:
            sys.exit("rescu_workflow.step_server: --idle must be a number of seconds > 0, "
                     f"got {value!r}")
    if not args:
        sys.exit("usage: python -m rescu_workflow.step_server [--idle=SECONDS] RUNNER [ARG ...]")
    runner, rest = args[0], args[1:]
    status = run_via_server(rest, runner, idle_s)
    if status is not None:
        sys.exit(status)
    run_file(runner, rest)


def _watch(conn: socket.socket) -> None:
    """Kill this process when its client goes (the connection ends)."""
    import threading

    def wait() -> None:
        try:
            conn.recv(1)
        except OSError:
            pass
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=wait, daemon=True).start()


if __name__ == "__main__":
    main()
