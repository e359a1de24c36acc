"""Snakemake adapter: base + enhanced caption (rescu.pipeline.caption)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.caption(snakemake.input.png, snakemake.input.meta, snakemake.input.result,
                 snakemake.output.json, snakemake.params.caption,
                 claims=snakemake.params.claims)
