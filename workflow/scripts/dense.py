"""Snakemake adapter: the dense RP source on one image (rescu.pipeline.dense)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.params.threads, torch=True)  # config threads: same floats under any --cores
pipeline.dense(snakemake.input.png, snakemake.input.meta, snakemake.output.json,
               snakemake.params.dense, snakemake.output.map)
