"""Snakemake adapter: the eight adaptive-parameter variants of RESCU-I on one image."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.ablation(snakemake.input.features, snakemake.input.meta, snakemake.output.json,
                  snakemake.params.stage1, snakemake.params.variants)
