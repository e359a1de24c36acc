"""Snakemake adapter: the ablation variants of RESCU-I (adaptive parameters, orientation mode)
and, with ablation.sources, the source rows (sparse-only, dense-only, sparse+dense) on one image."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
variants = snakemake.params.variants
outputs = dict(zip(snakemake.params.rows, snakemake.output))  # output order = row order
pipeline.ablation(snakemake.input.features, snakemake.input.meta, outputs,
                  snakemake.params.stage1, variants, png=snakemake.input.png,
                  dense_json=snakemake.input.get("dense"), dense_params=snakemake.params.dense)
