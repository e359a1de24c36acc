"""Evaluation over whole datasets: per-image metrics, tables, significance, plots, report.

``metrics`` (the IOD protocol on one image) is the base; the dataset-level tables,
curves and tests build on it; ``tables`` writes every table of a run and ``report``
renders them as one HTML page. Nothing is imported here.
"""
