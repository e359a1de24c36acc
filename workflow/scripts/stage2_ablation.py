"""Snakemake adapter: RESCU-II under each stage-II ablation variant on one image."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads, torch=True)  # config threads, not the job's core share
variants = snakemake.params.variants
outputs = dict(zip(variants, snakemake.output))  # output order = variant order
pipeline.stage2_ablation(snakemake.input.png, snakemake.input.meta, snakemake.input.stage1,
                         outputs, snakemake.params.stage2, variants,
                         snakemake.input.get("dense_map"), snakemake.params.dense)
