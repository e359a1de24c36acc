"""The quiet terminal of `make run` (rescu_workflow.runlog): progress, failures, the end."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rescu_workflow import runlog as R

SNAKEMAKE_OUTPUT = """\
Assuming unrestricted shared filesystem usage.
Building DAG of jobs...
Job stats:
job          count
---------  -------
caption          2
overlay          2
prepare          2
total            6

Select jobs to execute...
localrule prepare:
    input: a.jpg
    output: results/photos/prepared/a.png
    jobid: 3
    reason: Missing output files: results/photos/prepared/a.png
    wildcards: dataset=photos, image=a
Finished jobid: 3 (Rule: prepare)
1 of 6 steps (17%) done
rescu: dataset york_urban: ../shared/data/york_urban not found; skipped
Finished jobid: 4 (Rule: prepare)
2 of 6 steps (33%) done
Finished jobid: 5 (Rule: overlay)
3 of 6 steps (50%) done
[Thu Nov 26 16:00:00 2026]
Error in rule caption:
    message: None
    jobid: 7
    input: results/photos/scene-joint/b.json
    output: results/photos/final/b.json
    log: results/logs/photos/caption/b.log (check log file(s) for error details)
    wildcards: dataset=photos, image=b

Finished jobid: 8 (Rule: overlay)
4 of 6 steps (67%) done
Complete log(s): /x/.snakemake/log/2026.snakemake.log
"""


def test_monitor_keeps_progress_messages_and_failures() -> None:
    lines: list[str] = []
    t = iter(range(0, 1000, 10))
    mon = R.RunMonitor(lines.append, clock=lambda: float(next(t)))
    for ln in SNAKEMAKE_OUTPUT.splitlines():
        mon.feed(ln)
    mon.close()
    assert mon.images_total == 2 and mon.images_done == 2
    assert (mon.steps_done, mon.steps_total) == (4, 6)
    assert mon.snakemake_log == "/x/.snakemake/log/2026.snakemake.log"
    assert any(ln.startswith("rescu: dataset york_urban") for ln in lines)
    assert mon.failed == ["FAILED: step caption (dataset=photos, image=b); its log: "
                          "results/logs/photos/caption/b.log"]
    assert not any("reason:" in ln or "jobid" in ln or "Building" in ln for ln in lines)
    progress = [ln for ln in lines if ln.startswith("[")]
    assert progress and "of 2 images" in progress[-1] and "of 6 steps" in progress[-1]
    assert "left" in progress[-1]
    assert len(lines) <= 8


def test_run_prints_report_and_summary(tmp_path: Path) -> None:
    res = tmp_path / "results"
    (res / "photos" / "final").mkdir(parents=True)
    (res / "report").mkdir()
    (res / "report" / "index.html").write_text("<html></html>")
    (res / "photos" / "final" / "a.json").write_text(json.dumps(
        {"patterns": [{"count": 5}], "vanishing_point": None}))
    (res / "photos" / "final" / "b.json").write_text(json.dumps({"patterns": []}))
    script = tmp_path / "fake.py"
    script.write_text("import sys\nsys.stdout.write(" + repr(SNAKEMAKE_OUTPUT.replace(
        "Error in rule", "Note in rule")) + ")\n")

    class Out(list):
        def write(self, s): self.append(s)
        def flush(self): pass
        def isatty(self): return False

    out = Out()
    rc = R.run([sys.executable, str(script)], res, out=out)
    text = "".join(out)
    assert rc == 0
    assert text.rstrip().endswith(f"Report: {(res / 'report' / 'index.html').resolve()}")
    assert ("2 images: 1 with recurring patterns (1 RP), 1 without; a vanishing point "
            "in 0; 0 failed") in text
    assert (res / "logs" / "run.log").read_text().startswith("Assuming")
    assert len(text.splitlines()) <= 10


def test_a_message_repeated_by_each_parse_of_the_snakefile_is_shown_once():
    from rescu_workflow.runlog import RunMonitor

    shown = []
    mon = RunMonitor(shown.append)
    for _ in range(18):
        mon.feed("rescu: dataset 'chess': folder ../shared/data/chess not found, skipped")
    mon.feed("rescu: dataset 'cars': folder x not found, skipped")
    assert shown == ["rescu: dataset 'chess': folder ../shared/data/chess not found, skipped",
                     "rescu: dataset 'cars': folder x not found, skipped"]


def _fake_snakemake(tmp_path):
    """A 'snakemake' that, with --unlock, empties .snakemake/locks (as the real one)."""
    exe = tmp_path / "bin" / "snakemake"
    exe.parent.mkdir()
    exe.write_text("#!/bin/sh\nfor a in \"$@\"; do [ \"$a\" = --unlock ] && "
                   "rm -f .snakemake/locks/*; done\nexit 0\n")
    exe.chmod(0o755)
    return exe


def test_a_lock_left_by_a_killed_run_is_removed_in_one_line(tmp_path):
    from rescu_workflow.runlog import recover_lock

    exe = _fake_snakemake(tmp_path)
    locks = tmp_path / ".snakemake" / "locks"
    locks.mkdir(parents=True)
    (locks / "0.input.lock").write_text("x")
    said = []
    assert recover_lock([str(exe), "--cores", "2"], tmp_path, said.append)
    assert not any(locks.iterdir())
    assert len(said) == 1 and "was unlocked" in said[0]
    said.clear()
    assert recover_lock([str(exe)], tmp_path, said.append) and said == []  # no lock: quiet


def test_a_lock_held_by_a_live_snakemake_is_named_not_removed(tmp_path, monkeypatch):
    from rescu_workflow import runlog

    exe = _fake_snakemake(tmp_path)
    locks = tmp_path / ".snakemake" / "locks"
    locks.mkdir(parents=True)
    (locks / "0.input.lock").write_text("x")
    monkeypatch.setattr(runlog, "snakemake_pids", lambda w: [4242])  # a live one
    said = []
    assert not runlog.recover_lock([str(exe)], tmp_path, said.append)
    assert (locks / "0.input.lock").exists()
    assert len(said) == 1 and "pid 4242" in said[0] and "kill 4242" in said[0]


def test_snakemake_processes_are_found_by_name_and_folder(tmp_path):
    import subprocess
    import sys
    import time

    from rescu_workflow.runlog import snakemake_pids

    link = tmp_path / "snakemake"
    link.symlink_to(sys.executable)
    proc = subprocess.Popen([str(link), "-c", "import time; time.sleep(30)"], cwd=tmp_path)
    try:
        time.sleep(0.5)
        assert proc.pid in snakemake_pids(tmp_path)
        assert proc.pid not in snakemake_pids("/")       # another folder's
    finally:
        proc.kill()
