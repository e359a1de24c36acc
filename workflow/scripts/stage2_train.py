"""Snakemake adapter: train the per-image head (rescu.pipeline.stage2_train)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads, torch=True)  # config threads, not the job's core share
pipeline.stage2_train(snakemake.input.feats, snakemake.input.stage1, snakemake.output.ckpt,
                      snakemake.params.stage2)
