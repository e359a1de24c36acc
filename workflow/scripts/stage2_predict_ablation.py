"""Snakemake adapter: RESCU-II under each prediction-only stage-II variant on one image
(the run's own features and head)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads)  # the head runs in NumPy: no torch
variants = snakemake.params.variants
outputs = dict(zip(variants, snakemake.output))  # output order = variant order
pipeline.stage2_predict_variants(snakemake.input.feats, snakemake.input.ckpt,
                                 snakemake.input.stage1, snakemake.input.meta, outputs,
                                 snakemake.params.stage2, variants,
                                 snakemake.input.get("dense_map"), snakemake.params.dense)
