"""Snakemake adapter: RESCU-I on one image (rescu.pipeline.stage1)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.stage1(snakemake.input.features, snakemake.input.meta, snakemake.output.json,
                snakemake.output.h5, snakemake.params.stage1, method="rescu-i",
                png=snakemake.input.png, dense_json=snakemake.input.get("dense"),
                dense_params=snakemake.params.dense,
                dense_map_h5=snakemake.input.get("dense_map"))
