"""Evaluation over whole datasets: per-image metrics, tables, significance, plots, report.

``metrics`` (the IOD protocol on one image; box overlaps from :mod:`rescu.boxes`) is the
base; ``core`` (loading, RP tables, the one Wilcoxon helper, writers) builds the
dataset-level tables on it, and ``count_table``, ``vpd`` (vanishing points), ``ts``
(translation symmetry), ``failures`` and ``plots`` build on ``core``; ``tables`` writes
every table of a run and ``report`` renders them as one HTML page. What only the
benchmarks print is in ``benchmarks/_diagnostics.py``. Nothing is imported here.
"""
