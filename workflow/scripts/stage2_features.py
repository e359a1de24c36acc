"""Snakemake adapter: proposals + pooled backbone features (rescu.pipeline.stage2_features)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads, torch=True)  # config threads, not the job's core share
pipeline.stage2_features(snakemake.input.png, snakemake.input.meta, snakemake.input.stage1,
                         snakemake.output.h5, snakemake.params.stage2)
