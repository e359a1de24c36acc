"""The step server (rescu_workflow.step_server, python -m rescu_workflow.step_server): a job run in a child
of the server gets its streams, arguments and environment, exits with the status a process
of its own would, computes the same bytes, and does not outlive its client."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rescu_workflow import step_server

ROOT = Path(__file__).resolve().parents[1]
RUN_STEP = ROOT / "workflow" / "run_step.py"

pytestmark = pytest.mark.skipif(not step_server.available(),
                                reason="the step server needs Linux and socket.send_fds")

SCRIPT = '''
import os, sys
import numpy as np
x = snakemake.params.x
print("out", x, snakemake.wildcards.image, os.environ.get("RESCU_TEST_VALUE"))
print("err", x, file=sys.stderr)
rng = np.random.default_rng(0)
a = rng.standard_normal((64, 64))
if snakemake.params.get("torch"):
    import torch
    torch.set_num_threads(1)
    t = torch.nn.functional.conv2d(torch.from_numpy(a[None, None]).float(),
                                   torch.ones(1, 1, 3, 3) / 9.0)
    a = t.numpy()[0, 0].astype(np.float64)
np.save(snakemake.output[0], a @ a.T)
if x == 3:
    sys.exit(3)
if x == 4:
    raise ValueError("boom")
if x == 5:
    open(snakemake.output[0] + ".pid", "w").write(str(os.getpid()))
    import time
    time.sleep(60)
'''


def _job(out: Path, x: int, torch: bool = False) -> str:
    import json

    return json.dumps({"input": {"items": [], "names": {}},
                       "output": {"items": [str(out)], "names": {}},
                       "params": {"x": x, "torch": torch}, "threads": 1,
                       "wildcards": {"image": "img"}})


def _step(tmp_path: Path, x: int, server: bool, out: Path, torch: bool = False,
          **kw) -> subprocess.CompletedProcess:
    script = tmp_path / "step.py"
    script.write_text(SCRIPT)
    args = ([sys.executable, "-m", "rescu_workflow.step_server", "--idle=20"] if server else
            [sys.executable]) + [str(RUN_STEP)]
    env = {**os.environ, "RESCU_TEST_VALUE": "v1"}
    return subprocess.run(args + [str(script), _job(out, x, torch), str(tmp_path / "log")],
                          capture_output=True, text=True, env=env, cwd=tmp_path, **kw)


@pytest.mark.parametrize("x", [0, 3, 4])
def test_a_job_through_the_server_ends_as_its_own_process_would(tmp_path, x):
    own = _step(tmp_path, x, False, tmp_path / "own.npy")
    served = _step(tmp_path, x, True, tmp_path / "served.npy")
    assert served.returncode == own.returncode == {0: 0, 3: 3, 4: 1}[x]
    assert served.stdout == own.stdout == f"out {x} img v1\n"
    assert served.stderr.startswith(f"err {x}\n")
    if x == 4:
        assert "ValueError: boom" in served.stderr and "ValueError: boom" in own.stderr
    assert (tmp_path / "served.npy").read_bytes() == (tmp_path / "own.npy").read_bytes()


def test_a_torch_step_computes_the_same_bytes_through_the_server(tmp_path):
    own = _step(tmp_path, 0, False, tmp_path / "own.npy", torch=True)
    served = _step(tmp_path, 0, True, tmp_path / "served.npy", torch=True)
    assert own.returncode == served.returncode == 0, served.stderr
    assert (tmp_path / "served.npy").read_bytes() == (tmp_path / "own.npy").read_bytes()


def _long_job(tmp_path: Path) -> tuple[subprocess.Popen, int]:
    """A job that sleeps, started through the server: (its client, the job's pid)."""
    script = tmp_path / "step.py"
    script.write_text(SCRIPT)
    out = tmp_path / "long.npy"
    client = subprocess.Popen([sys.executable, "-m", "rescu_workflow.step_server", "--idle=20",
                               str(RUN_STEP), str(script), _job(out, 5),
                               str(tmp_path / "log")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp_path)
    pid_file = Path(str(out) + ".pid")
    end = time.monotonic() + 60
    # the job writes its pid after creating the file: wait for the digits, not the name
    while not (pid_file.exists() and pid_file.read_text().strip()) and time.monotonic() < end:
        time.sleep(0.05)
    return client, int(pid_file.read_text())


def test_a_job_does_not_outlive_its_client(tmp_path):
    client, child = _long_job(tmp_path)
    assert child != client.pid                      # the job ran in the server's child
    client.send_signal(signal.SIGKILL)
    client.wait()
    end = time.monotonic() + 10
    while time.monotonic() < end and Path(f"/proc/{child}").exists():
        time.sleep(0.05)
    assert not Path(f"/proc/{child}").exists()


def test_a_signal_to_the_client_reaches_the_job(tmp_path):
    client, child = _long_job(tmp_path)
    client.send_signal(signal.SIGTERM)
    _, err = client.communicate(timeout=20)
    assert client.returncode == 1 and b"without an exit status" in err
    assert not Path(f"/proc/{child}").exists()


@pytest.fixture
def short():
    """A folder with a short path (a Unix socket's path is at most 107 bytes)."""
    import shutil
    import tempfile

    d = tempfile.mkdtemp(prefix="rs", dir="/tmp")
    yield d
    shutil.rmtree(d, ignore_errors=True)


def test_the_server_ends_when_idle_and_a_new_one_starts(tmp_path, short):
    runner = tmp_path / "runner.py"
    runner.write_text("import sys\n"
                      "open(sys.argv[1], 'w').write(' '.join(sys.argv[2:]))\n")
    directory = short
    path = step_server.socket_path(directory)
    status = step_server.run_via_server([str(tmp_path / "a.txt"), "x", "y"], str(runner),
                                        idle_s=0.5, directory=directory)
    assert status == 0 and (tmp_path / "a.txt").read_text() == "x y"
    end = time.monotonic() + 30
    while os.path.exists(path) and time.monotonic() < end:
        time.sleep(0.05)
    assert not os.path.exists(path)                 # ended, its socket removed
    Path(path).touch()                              # a socket file left by a killed one
    status = step_server.run_via_server([str(tmp_path / "b.txt"), "z"], str(runner),
                                        idle_s=0.5, directory=directory)
    assert status == 0 and (tmp_path / "b.txt").read_text() == "z"


def test_no_server_inside_a_slurm_job(monkeypatch, tmp_path):
    monkeypatch.setenv("SLURM_JOB_ID", "1")
    assert not step_server.available()
    assert step_server.run_via_server(["x", "{}"], str(RUN_STEP),
                                      directory=str(tmp_path)) is None


def test_servers_differ_by_the_thread_settings_libraries_read_at_load():
    a = step_server.socket_path("/d", env={"OMP_NUM_THREADS": "1"}, path=["p"])
    assert a == step_server.socket_path("/d", env={"OMP_NUM_THREADS": "1", "HOME": "h"},
                                        path=["p"])
    assert a != step_server.socket_path("/d", env={"OMP_NUM_THREADS": "2"}, path=["p"])
    assert a != step_server.socket_path("/d", env={"OMP_NUM_THREADS": "1"}, path=["q"])


@pytest.mark.parametrize("idle", ["0", "-1", "soon"])
def test_an_idle_time_that_is_not_positive_is_refused(tmp_path, idle):
    r = subprocess.run([sys.executable, "-m", "rescu_workflow.step_server", f"--idle={idle}",
                        str(RUN_STEP), "x.py", "{}"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 1 and "--idle must be a number of seconds > 0" in r.stderr


# --------------------------------------------------------------- only this user's
WRITER = "import sys\nopen(sys.argv[1], 'w').write('ran')\n"


def test_socket_and_lock_live_in_a_folder_only_this_user_may_enter(tmp_path, short):
    import stat

    runner = tmp_path / "runner.py"
    runner.write_text(WRITER)
    assert step_server.run_via_server([str(tmp_path / "a")], str(runner), idle_s=0.5,
                                      directory=short) == 0
    folder = step_server.private_dir(short)
    assert os.path.dirname(step_server.socket_path(short)) == folder
    st = os.lstat(folder)
    assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700
    assert st.st_uid == os.getuid()
    lock = step_server.socket_path(short) + ".lock"
    assert stat.S_IMODE(os.lstat(lock).st_mode) == 0o600


@pytest.mark.parametrize("plant", ["open folder", "link", "file"])
def test_a_socket_folder_others_could_plant_in_is_refused(tmp_path, short, capsys, plant):
    runner = tmp_path / "runner.py"
    runner.write_text(WRITER)
    folder = step_server.private_dir(short)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if plant == "open folder":
        os.mkdir(folder)
        os.chmod(folder, 0o770)
    elif plant == "link":
        os.symlink(elsewhere, folder)
    else:
        Path(folder).write_text("x")
    assert step_server.run_via_server([str(tmp_path / "a")], str(runner), idle_s=0.5,
                                      directory=short) is None
    assert not (tmp_path / "a").exists() and not any(elsewhere.iterdir())
    err = capsys.readouterr().err
    assert "rescu step server: not used" in err and folder in err
    assert "runs in its own process" in err


def test_a_lock_planted_as_a_link_is_not_followed(tmp_path, short, capsys):
    runner = tmp_path / "runner.py"
    runner.write_text(WRITER)
    target = tmp_path / "precious"
    target.write_text("keep me")
    os.mkdir(step_server.private_dir(short), 0o700)
    os.symlink(target, step_server.socket_path(short) + ".lock")
    assert step_server.run_via_server([str(tmp_path / "a")], str(runner), idle_s=0.5,
                                      directory=short) is None
    assert target.read_text() == "keep me"
    assert "without following links" in capsys.readouterr().err


def test_a_socket_path_too_long_for_unix_is_refused(tmp_path, capsys):
    deep = tmp_path / ("d" * 100)
    deep.mkdir()
    assert step_server.run_via_server(["x"], str(tmp_path / "r.py"),
                                      directory=str(deep)) is None
    assert "too long" in capsys.readouterr().err


OTHER_UID = 65534  # nobody
as_root = pytest.mark.skipif(os.getuid() != 0, reason="a second uid needs root to act as it")


def _python_of(uid: int) -> str:
    """A Python interpreter that ``uid`` may run (the test's may sit in root's home)."""
    import shutil

    for cand in (sys.executable, "/usr/bin/python3", shutil.which("python3") or ""):
        try:
            if cand and subprocess.run([cand, "-c", "import socket; socket.send_fds"],
                                       user=uid, capture_output=True,
                                       timeout=30).returncode == 0:
                return cand
        except OSError:
            continue
    pytest.skip(f"no Python 3.9+ that uid {uid} may run")


@as_root
def test_a_folder_of_another_user_is_refused(tmp_path, short, capsys):
    folder = step_server.private_dir(short)
    os.mkdir(folder, 0o700)
    os.chown(folder, OTHER_UID, OTHER_UID)
    assert step_server.run_via_server(["x"], str(tmp_path / "r.py"), directory=short) is None
    assert f"belongs to uid {OTHER_UID}" in capsys.readouterr().err


@as_root
def test_the_client_refuses_a_server_of_another_user(short):
    """A socket squatted by another user gets neither the environment nor the streams."""
    os.chmod(short, 0o777)
    path = os.path.join(short, "squat.sock")
    got = os.path.join(short, "got")
    squatter = subprocess.Popen(
        [_python_of(OTHER_UID), "-c",
         "import socket, sys\n"
         "s = socket.socket(socket.AF_UNIX); s.bind(sys.argv[1]); s.listen(1)\n"
         "import os; os.chmod(sys.argv[1], 0o777)\n"
         "open(sys.argv[2] + '.ready', 'w').close()\n"
         "c, _ = s.accept(); c.settimeout(5)\n"
         "try:\n    data = c.recv(1 << 16)\nexcept OSError:\n    data = b''\n"
         "open(sys.argv[2], 'wb').write(data)\n", path, got],
        user=OTHER_UID)
    try:
        # wait until it listens and anyone may connect: the socket file exists from bind
        # on, and a connection before listen is refused (no server, nothing to refuse)
        end = time.monotonic() + 20
        while not os.path.exists(got + ".ready") and time.monotonic() < end:
            time.sleep(0.02)
        with pytest.raises(step_server.UnsafeError, match=f"uid {OTHER_UID}"):
            step_server._connect(path)
        squatter.wait(timeout=20)
        assert Path(got).read_bytes() == b""        # it received nothing
    finally:
        squatter.kill()


@as_root
def test_the_server_refuses_a_client_of_another_user(tmp_path, short):
    """Another user who reaches the socket does not get a job run as its owner."""
    runner = tmp_path / "runner.py"
    runner.write_text(WRITER)
    assert step_server.run_via_server([str(tmp_path / "first")], str(runner), idle_s=20,
                                      directory=short) == 0     # a server is running
    path = step_server.socket_path(short)
    os.chmod(short, 0o755)
    os.chmod(step_server.private_dir(short), 0o755)  # the folder's defence taken away:
    os.chmod(path, 0o777)                             # the peer check alone remains
    attacker = Path(short) / "attacker.py"
    marker = tmp_path / "pwned"
    attacker.write_text(
        "import json, socket, struct, sys\n"
        "s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1])\n"
        "req = json.dumps({'argv': [sys.argv[3]], 'runner': sys.argv[2], 'cwd': '/',\n"
        "                  'env': {}, 'path': sys.path}).encode()\n"
        "s.settimeout(10)\n"
        "try:\n"  # refused at once: the send may already meet the closed socket
        "    socket.send_fds(s, [struct.pack('!I', len(req)) + req], [0, 1, 2])\n"
        "    got = s.recv(8)\n"
        "except (ConnectionResetError, BrokenPipeError):\n    got = b''\n"
        "print('served' if got else 'closed')\n")
    r = subprocess.run([_python_of(OTHER_UID), str(attacker), path, str(runner), str(marker)],
                       user=OTHER_UID, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "closed", r.stderr   # no pid, no status
    time.sleep(0.5)
    assert not marker.exists()
