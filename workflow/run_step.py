"""Run one adapter of ``workflow/scripts`` for a per-image rule, without Snakemake.

    python workflow/run_step.py SCRIPT JOB LOG

Snakemake's ``script:`` directive starts each job's Python with a preamble that imports
Snakemake (its I/O, logging and shell modules) to unpickle the job: a job that does
nothing takes 0.26-0.30 s that way and 0.19-0.24 s through this file
(``benchmarks/speed/job_overhead.py``), and a run of the paper's tables has about 4,700
jobs, most of them short.
The per-image rules therefore run their adapter through this file from ``shell:``
(``step_params`` and ``STEP_SHELL`` in ``workflow/rules/common.smk``): ``JOB`` is the
job as JSON (its inputs, outputs, parameters, threads and wildcards, written
by Snakemake while it schedules), ``LOG`` the job's log file. The adapter runs as the
main module with a global ``snakemake`` that has what the directive's object has for
it: ``input``, ``output`` and ``log`` (lists of paths, each name an attribute, and
``get(name, default)``), ``params`` (each parameter an attribute), ``wildcards`` and
``threads``. Nothing of Snakemake is imported.
"""

from __future__ import annotations

import json
import runpy
import sys
from typing import Any


class Names(list):
    """A list whose named items (or slices) are also attributes, like Snakemake's
    named lists: ``names`` maps a name to ``[start, end]`` (``end`` None: the item at
    ``start``; else the items ``start:end``, as a list)."""

    def __init__(self, items: list[Any], names: dict[str, list[Any]]) -> None:
        super().__init__(items)
        self._names = {k: tuple(v) for k, v in names.items()}

    def __getattr__(self, name: str) -> Any:
        names = self.__dict__.get("_names", {})
        if name not in names:
            raise AttributeError(f"no item named {name!r} (named: {sorted(names)})")
        start, end = names[name]
        return self[start] if end is None else list(self[start:end])

    def get(self, name: str, default: Any = None) -> Any:
        """The item named ``name``, or ``default``."""
        return getattr(self, name) if name in self._names else default


def job_object(job: dict[str, Any], log: list[str]) -> Any:
    """The ``snakemake`` global of an adapter from the job's JSON (:data:`__doc__`)."""
    from types import SimpleNamespace

    def named(part: dict[str, Any]) -> Names:
        return Names(part["items"], part["names"])

    params = job["params"]
    return SimpleNamespace(
        input=named(job["input"]), output=named(job["output"]),
        params=Names(list(params.values()),
                     {k: [i, None] for i, k in enumerate(params)}),
        wildcards=Names(list(job["wildcards"].values()),
                        {k: [i, None] for i, k in enumerate(job["wildcards"])}),
        log=Names(log, {}), threads=int(job["threads"]))


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        sys.exit("usage: python workflow/run_step.py SCRIPT JOB [LOG ...]")
    script, job = argv[0], json.loads(argv[1])
    runpy.run_path(script, init_globals={"snakemake": job_object(job, list(argv[2:]))},
                   run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
