"""Snakemake adapter: proposals + pooled backbone features (rescu.pipeline.stage2_features),
then the per-image head trained on them (rescu.pipeline.stage2_train), in one process."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads, torch=True)  # config threads, not the job's core share
pipeline.stage2_features(snakemake.input.png, snakemake.input.meta, snakemake.input.stage1,
                         snakemake.output.h5, snakemake.params.stage2)
pipeline.limit_threads(snakemake.params.head_threads)  # the head's own thread count
pipeline.stage2_train(snakemake.output.h5, snakemake.input.stage1, snakemake.output.ckpt,
                      snakemake.params.stage2)
