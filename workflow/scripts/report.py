"""Snakemake adapter: the self-contained HTML report (rescu.evaluation.report)."""
from rescu.pipeline import setup_logging
from rescu.evaluation.report import build_run_report

setup_logging(snakemake.log[0])
build_run_report(snakemake.output.html, snakemake.params.results, snakemake.params.samples,
                 snakemake.params.evaluation, tables=snakemake.input.tables,
                 report=snakemake.params.report, skipped=snakemake.params.skipped)
