"""Snakemake adapter: RESCU-II instances (rescu.pipeline.stage2_predict)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads)  # the head runs in NumPy: no torch
pipeline.stage2_predict(snakemake.input.feats, snakemake.input.ckpt, snakemake.input.stage1,
                        snakemake.output.json, snakemake.input.meta, snakemake.params.stage2,
                        snakemake.input.get("dense_map"), snakemake.params.dense)
