"""Snakemake adapter: the explicit-line (LSD) VP baseline (rescu.pipeline.line_vp)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.line_vp(snakemake.input.png, snakemake.input.meta, snakemake.output.json,
                 snakemake.params.scene)
