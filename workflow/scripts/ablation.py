"""Snakemake adapter: the ablation variants of RESCU-I (adaptive parameters, orientation mode) on one image."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
variants = snakemake.params.variants
outputs = dict(zip(variants, snakemake.output))  # output order = variant order
pipeline.ablation(snakemake.input.features, snakemake.input.meta, outputs,
                  snakemake.params.stage1, variants, png=snakemake.input.png)
