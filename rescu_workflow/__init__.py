"""The workflow's machinery beside the library: what runs RESCU's Snakemake pipeline
faster and quieter, and nothing a library user calls.

``step_server`` (per-image jobs served by a process that has imported their libraries
once), ``code_deps`` (the library files each workflow step's code depends on, read from
``rescu``'s import graph: a rule reruns when one of them changes) and ``runlog`` (the
quiet terminal of ``make run``). ``rescu/`` imports nothing from here
(``tests/test_layout.py``).
"""
