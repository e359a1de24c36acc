"""Snakemake adapter: load, orient, downscale one photo (rescu.pipeline.prepare)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.prepare(snakemake.input.image, snakemake.output.png, snakemake.output.meta,
                 image_name=snakemake.params.image_name, max_side=snakemake.params.max_side,
                 min_side=snakemake.params.min_side,
                 max_pixels=snakemake.params.max_pixels)
