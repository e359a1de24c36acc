"""Snakemake adapter: SIFT features to HDF5 (rescu.pipeline.features)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.features(snakemake.input.png, snakemake.input.meta, snakemake.output.h5,
                  snakemake.params.features)
