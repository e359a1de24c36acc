"""A quiet terminal for a pipeline run: one progress line, warnings and failures, and at
the end where the report is and what was found.

``python -m rescu_workflow.runlog [--verbose] [--results DIR] -- snakemake --cores 2 ...``
runs the command, keeps its full output in ``<results>/logs/run.log`` (Snakemake also keeps
its own log under ``.snakemake/log/``) and prints instead:

* a progress line ``[##....] 12 of 30 images, 150 of 423 steps, about 6 min left``
  (rewritten in place on a terminal; elsewhere printed at every tenth of the steps);
* the lines that need a person: ``rescu:`` messages (a dataset skipped, a peer not
  installed), warnings, and each failed step as one line naming its rule, wildcards and
  log file;
* at the end the path of the HTML report and one line of what was found
  (:func:`results_summary`), or why the run stopped.

With ``--verbose`` the command's output is passed through unchanged. :class:`RunMonitor`
holds the parsing and is tested on its own; it reads Snakemake's text output (job
blocks, ``Finished jobid: N (Rule: R)``, ``N of M steps (P%) done``, ``Error in rule
R:``), not Snakemake's API.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Sequence, TextIO

IMAGE_RULE = "overlay"
"""The last per-image step: one finished job of it is one image done."""

_STEPS = re.compile(r"^(\d+) of (\d+) steps \(.*\) done")
_STAT = re.compile(r"^(\w+)\s+(\d+)$")
_FINISHED = re.compile(r"^Finished jobid: \d+ \(Rule: (\w+)\)")
_ERROR = re.compile(r"^Error in rule (\w+):")
_PASS = re.compile(r"^(rescu:|WARNING|Warning:|MissingInputException|WorkflowError|"
                   r"InputFunctionException|SyntaxError|KeyError|ValueError|"
                   r"IncompleteFilesException|LockException|Error:)")


def _minutes(seconds: float) -> str:
    if seconds < 90:
        return f"{max(seconds, 1):.0f} s"
    return f"{seconds / 60:.0f} min"


class RunMonitor:
    """Turns Snakemake's output, line by line, into the few lines a person needs.

    Parameters
    ----------
    emit : callable
        Receives each line to print (without newline).
    progress : callable, optional
        Receives the progress line whenever it changes (a terminal rewrites it in
        place); None: progress lines go to ``emit`` at every tenth of the steps.
    clock : callable
        Seconds, monotonic (for the estimate of the time left).
    """

    def __init__(self, emit: Callable[[str], None],
                 progress: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.emit, self.progress, self.clock = emit, progress, clock
        self.start = clock()
        self.steps_done = self.steps_total = 0
        self.images_done = self.images_total = 0
        self.failed: list[str] = []
        self.nothing_to_do = False
        self.snakemake_log: str | None = None
        self._in_stats = False
        self._error: dict[str, str] | None = None
        self._last_tenth = -1
        self._first_done_at: float | None = None
        self._first_done = 0
        self._said: set[str] = set()

    # ------------------------------------------------------------------ lines
    def feed(self, line: str) -> None:
        """Read one line of the command's output."""
        s = line.rstrip("\n")
        t = s.strip()
        if self._error is not None:
            if t and ":" in t and s.startswith((" ", "\t")):
                k, _, v = t.partition(":")
                self._error[k.strip()] = v.strip()
                return
            self._flush_error()
        if t == "Job stats:":
            self._in_stats = True
            return
        if self._in_stats:
            m = _STAT.match(t)
            if m and m.group(1) == IMAGE_RULE and not self.images_total:
                self.images_total = int(m.group(2))
            if m and m.group(1) == "total":
                self._in_stats = False
            return
        if t.startswith("Nothing to be done"):
            self.nothing_to_do = True
            return
        if t.startswith("Complete log(s):") or t.startswith("Complete log:"):
            self.snakemake_log = t.split(":", 1)[1].strip()
            return
        m = _FINISHED.match(t)
        if m:
            if m.group(1) == IMAGE_RULE:
                self.images_done += 1
            return
        m = _STEPS.match(t)
        if m:
            self._steps(int(m.group(1)), int(m.group(2)))
            return
        m = _ERROR.match(t)
        if m:
            self._error = {"rule": m.group(1)}
            return
        if _PASS.match(t) and "libpng" not in t and t not in self._said:
            self._said.add(t)  # Snakemake parses the Snakefile again for some steps: once
            self._say(t)

    def close(self) -> None:
        """End of the output: report a pending failure."""
        if self._error is not None:
            self._flush_error()

    # ------------------------------------------------------------------ state
    def _say(self, text: str) -> None:
        if self.progress is not None:
            self.progress("")  # clear the progress line before a message
        self.emit(text)
        if self.progress is not None and self.steps_total:
            self.progress(self.progress_line())

    def _flush_error(self) -> None:
        e, self._error = self._error or {}, None
        what = e.get("wildcards", "")
        log = e.get("log", "").replace(" (check log file(s) for error details)", "")
        text = f"FAILED: step {e.get('rule', '?')}" + (f" ({what})" if what else "")
        text += f"; its log: {log}" if log else ""
        self.failed.append(text)
        self._say(text)

    def _steps(self, done: int, total: int) -> None:
        now = self.clock()
        if self._first_done_at is None:  # the rate starts at the first finished step
            self._first_done_at, self._first_done = now, done - 1
        self.steps_done, self.steps_total = done, total
        line = self.progress_line()
        if self.progress is not None:
            self.progress(line)
        else:
            tenth = 10 * done // max(total, 1)
            if tenth != self._last_tenth:
                self._last_tenth = tenth
                self.emit(line)

    def eta_seconds(self) -> float | None:
        """Seconds left at the mean rate since the first finished step; None before two
        steps have finished."""
        if self._first_done_at is None or self.steps_done - self._first_done < 2:
            return None
        rate = (self.clock() - self._first_done_at) / (self.steps_done - self._first_done)
        return rate * (self.steps_total - self.steps_done)

    def progress_line(self) -> str:
        """``[####......] 12 of 30 images, 150 of 423 steps, about 6 min left``."""
        frac = self.steps_done / max(self.steps_total, 1)
        bar = "#" * round(20 * frac) + "." * (20 - round(20 * frac))
        parts = []
        if self.images_total:
            parts.append(f"{self.images_done} of {self.images_total} images")
        parts.append(f"{self.steps_done} of {self.steps_total} steps")
        eta = self.eta_seconds()
        if self.steps_done >= self.steps_total:
            parts.append(f"done in {_minutes(self.clock() - self.start)}")
        elif eta is not None:
            parts.append(f"about {_minutes(eta)} left")
        return f"[{bar}] " + ", ".join(parts)


# ----------------------------------------------------------------------------- results
def results_summary(results: str | Path) -> str:
    """One line of what a run found, from ``<results>/<dataset>/final/*.json``: images,
    those with recurring patterns, RPs, supported VPs, failures and images with a failed
    step whose previous result was kept. Empty when there is no final JSON."""
    results = Path(results)
    n = with_rp = rps = vps = failed = degraded = 0
    for f in sorted(results.glob("*/final/*.json")):
        try:
            d = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        n += 1
        pats = [p for p in d.get("patterns") or [] if int(p.get("count", 0)) >= 2]
        with_rp += bool(pats)
        rps += len(pats)
        vps += d.get("vanishing_point") is not None
        f_rec = d.get("failure") or {}
        failed += bool(f_rec) and not f_rec.get("degraded_to")
        degraded += bool(f_rec.get("degraded_to"))
    if not n:
        return ""
    return (f"{n} images: {with_rp} with recurring patterns ({rps} RP{'s' * (rps != 1)}), "
            f"{n - with_rp} without; a vanishing point in {vps}; {failed} failed"
            + (f", {degraded} with a failed step (the step before it kept)" if degraded else ""))


def _results_dir(argv: Sequence[str], default: str) -> str:
    for a in argv:
        if a.startswith("results_dir="):
            return a.split("=", 1)[1]
    try:                              # the checkout's overrides, then the package defaults
        import yaml

        user = yaml.safe_load(Path("config/config.yaml").read_text()) or {}
        if "results_dir" in user:
            return str(user["results_dir"])
        from rescu.params import config_defaults

        return str(config_defaults()["results_dir"])
    except (OSError, KeyError, TypeError, ValueError, AttributeError):
        return default


def snakemake_pids(workdir: str | Path) -> list[int]:
    """Process ids of the Snakemake processes (other than this one and its parent)
    whose working folder is ``workdir`` (from ``/proc``; empty where there is none)."""
    import os

    root = os.path.realpath(workdir)
    mine = {os.getpid(), os.getppid()}
    pids = []
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            pid = int(entry.name)
            if pid in mine:
                continue
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            if not any(Path(a.decode(errors="replace")).name == "snakemake" or a == b"snakemake"
                       for a in argv[:3]):
                continue
            if os.path.realpath(os.readlink(entry / "cwd")) == root:
                pids.append(pid)
        except (OSError, ValueError):
            continue
    return sorted(pids)


def recover_lock(cmd: Sequence[str], workdir: str | Path = ".",
                 emit: Callable[[str], None] = print) -> bool:
    """Before a Snakemake run in ``workdir``: a lock left by a killed run
    (``.snakemake/locks`` not empty, no Snakemake of this folder alive) is removed with
    ``cmd --unlock``, said in one line; a lock held by a live Snakemake is said in one
    line naming its pid, and False returned (the run would fail). True: go on."""
    locks = Path(workdir) / ".snakemake" / "locks"
    if not cmd or Path(cmd[0]).name != "snakemake" or not locks.is_dir() \
            or not any(locks.iterdir()):
        return True
    alive = snakemake_pids(workdir)
    if alive:
        emit(f"Another Snakemake (pid {', '.join(map(str, alive))}) is running in this "
             f"folder and holds its lock: wait for it to finish, or stop it (kill "
             f"{alive[0]}) and run again.")
        return False
    proc = subprocess.run([*cmd, "--unlock"], cwd=workdir, capture_output=True, text=True)
    if proc.returncode != 0:
        emit(f"A stopped run left its lock and unlocking failed (exit {proc.returncode}); "
             f"run: snakemake --unlock")
        return False
    emit("A stopped run had left its lock; no Snakemake of this folder is running, so it "
         "was unlocked (snakemake --unlock). Going on.")
    return True


def run(cmd: Sequence[str], results: str | Path, out: TextIO = sys.stdout,
        verbose: bool = False) -> int:
    """Run ``cmd``, print what :class:`RunMonitor` keeps (everything with ``verbose``),
    and the report's path and :func:`results_summary` at the end; return its exit code.
    The full output goes to ``<results>/logs/run.log``."""
    results = Path(results)
    log_path = results / "logs" / "run.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    tty = out.isatty()
    width = [0]

    def progress(line: str) -> None:
        out.write("\r" + line.ljust(width[0]) + ("" if line else "\r"))
        width[0] = max(width[0], len(line))
        out.flush()

    def emit(line: str) -> None:
        out.write(line + "\n")
        out.flush()

    workdir = "."
    for flag, value in zip(cmd, list(cmd[1:]) + [""]):
        if flag in ("--directory", "-d"):
            workdir = value
    if not recover_lock(cmd, workdir, emit):
        return 1
    mon = RunMonitor(emit, progress if tty else None)
    proc = subprocess.Popen(list(cmd), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, bufsize=1)
    tail: list[str] = []
    with open(log_path, "w") as log:
        assert proc.stdout is not None
        for line in proc.stdout:
            log.write(line)
            if verbose:
                out.write(line)
                continue
            tail = (tail + [line.rstrip()])[-25:]
            mon.feed(line)
    rc = proc.wait()
    mon.close()
    if tty and not verbose:
        out.write("\n")
    report = results / "report" / "index.html"
    if rc != 0:
        if not verbose and not mon.failed and not mon.steps_total:
            emit("\n".join(tail[-15:]))  # stopped before any step: say why
        emit(f"The run stopped (exit code {rc}); {len(mon.failed)} step(s) failed. Full "
             f"log: {log_path}")
        return rc
    if mon.nothing_to_do:
        emit("Nothing to do: every result is up to date.")
    summary = results_summary(results)
    if summary:
        emit(summary)
    emit(f"Report: {report.resolve()}" if report.exists() else f"Full log: {log_path}")
    return rc


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rescu_workflow.runlog [--verbose] [--results DIR] -- COMMAND ...``."""
    p = argparse.ArgumentParser(prog="python -m rescu_workflow.runlog",
                                description="Run a pipeline command with a quiet terminal.")
    p.add_argument("--verbose", action="store_true", help="pass the full output through")
    p.add_argument("--results", default=None,
                   help="the run's results folder (default: results_dir= in the command, "
                        "else config/config.yaml's or the default's)")
    p.add_argument("command", nargs=argparse.REMAINDER)
    a = p.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    if not cmd:
        p.error("no command given")
    return run(cmd, a.results or _results_dir(cmd, "results"), verbose=a.verbose)


if __name__ == "__main__":
    sys.exit(main())
