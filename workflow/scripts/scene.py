"""Snakemake adapter: VP, translation symmetry, counts, rectified views (rescu.pipeline.scene)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.scene(snakemake.input.png, snakemake.input.meta, snakemake.input.result,
               snakemake.output.json, snakemake.output.rectified, snakemake.params.scene)
