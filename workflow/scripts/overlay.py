"""Snakemake adapter: the overlay picture of what was found (rescu.pipeline.overlay)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.overlay(snakemake.input.png, snakemake.input.meta, snakemake.input.result,
                 snakemake.output.png, mode=snakemake.params.mode)
