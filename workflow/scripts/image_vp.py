"""Snakemake adapter: the image's VPs from RP rows and lines together (rescu.pipeline.image_vp)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
gt = getattr(snakemake.input, "gt", None)  # the dataset's calibration: the true focal length
pipeline.image_vp(snakemake.input.png, snakemake.input.meta, snakemake.input.result,
                  snakemake.output.json, snakemake.params.scene,
                  pipeline.dataset_focal(gt, snakemake.input.meta) if gt else None)
