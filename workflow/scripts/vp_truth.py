"""Snakemake adapter: derived VP ground truth of rectified photos (rescu.pipeline.vp_truth)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.vp_truth(snakemake.input.annotations, snakemake.output[0])
