"""Memory of a whole command as ``ps`` sees it: every process it starts, step servers too.

    python benchmarks/speed/tree_memory.py [--interval S] [--json FILE] -- make run

Runs the command and, every ``--interval`` seconds until it exits, reads the memory of
every process of the run: the command's descendants, and the step servers
(:mod:`rescu_workflow.step_server`) and their forked step processes, which run in sessions of
their own and outlive the job that started them (``/usr/bin/time`` and Snakemake's
``benchmark:`` files see neither: they count the small client processes). A step server
already running when the command starts is counted too when the command's jobs use it
(its forks are then the command's work).

Prints, for the whole run: the peak of the summed proportional set size (PSS: each
shared page counted once, split among the processes that share it; what the run adds to
the machine's used memory), the peak of the summed resident set size (RSS: shared pages
counted in every process, an upper bound), the largest single process's RSS and its
command, and the most processes at once; and the command's wall seconds and exit status.
Sampling misses peaks shorter than the interval. Linux only (``/proc``; ``psutil``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def _is_server(p) -> bool:
    try:
        return "rescu_workflow.step_server" in " ".join(p.cmdline()) and p.uids().real == os.getuid()
    except Exception:
        return False


def tracked(root_pid: int, psutil) -> list:
    """The processes of the run: descendants of ``root_pid``, and every step server of
    this user with its descendants."""
    procs = {}
    try:
        root = psutil.Process(root_pid)
        for p in [root, *root.children(recursive=True)]:
            procs[p.pid] = p
    except psutil.NoSuchProcess:
        pass
    for p in psutil.process_iter():
        if p.pid in procs or not _is_server(p):
            continue
        procs[p.pid] = p
        try:
            for c in p.children(recursive=True):
                procs[c.pid] = c
        except psutil.NoSuchProcess:
            pass
    return list(procs.values())


def sample(procs: list, psutil) -> tuple[float, float, float, str, int]:
    """``(sum PSS, sum RSS, max RSS, its command, n)`` in bytes over ``procs``."""
    pss = rss = top = 0.0
    top_cmd, n = "", 0
    for p in procs:
        try:
            m = p.memory_full_info()
            cmd = " ".join(p.cmdline())[:120]
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
        n += 1
        pss += getattr(m, "pss", m.rss)
        rss += m.rss
        if m.rss > top:
            top, top_cmd = float(m.rss), cmd
    return pss, rss, top, top_cmd, n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interval", type=float, default=0.5, help="seconds between samples")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    ap.add_argument("cmd", nargs=argparse.REMAINDER, help="-- the command")
    a = ap.parse_args(argv)
    cmd = a.cmd[1:] if a.cmd[:1] == ["--"] else a.cmd
    if not cmd:
        ap.error("no command (give it after --)")
    import psutil

    t0 = time.monotonic()
    proc = subprocess.Popen(cmd)
    peak = {"pss": 0.0, "rss": 0.0, "max_rss": 0.0, "max_rss_cmd": "", "processes": 0}
    while proc.poll() is None:
        pss, rss, top, top_cmd, n = sample(tracked(proc.pid, psutil), psutil)
        peak["pss"] = max(peak["pss"], pss)
        peak["rss"] = max(peak["rss"], rss)
        peak["processes"] = max(peak["processes"], n)
        if top > peak["max_rss"]:
            peak["max_rss"], peak["max_rss_cmd"] = top, top_cmd
        time.sleep(a.interval)
    wall = time.monotonic() - t0
    mib = 2.0 ** 20
    out = {"command": " ".join(cmd), "exit": proc.returncode, "wall_s": round(wall, 1),
           "peak_sum_pss_mib": round(peak["pss"] / mib), "peak_sum_rss_mib":
           round(peak["rss"] / mib), "peak_process_rss_mib": round(peak["max_rss"] / mib),
           "peak_process": peak["max_rss_cmd"], "most_processes": peak["processes"],
           "interval_s": a.interval}
    text = json.dumps(out, indent=1)
    print(text, file=sys.stderr)
    if a.json:
        with open(a.json, "w") as f:
            f.write(text + "\n")
    return int(proc.returncode != 0)


if __name__ == "__main__":
    raise SystemExit(main())
