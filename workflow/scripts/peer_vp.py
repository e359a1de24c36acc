"""Snakemake adapter: a peer's VPs, lu-vp-detect (rescu.pipeline.peer_vp)."""
from rescu import pipeline

pipeline.setup_logging(snakemake.log[0])
pipeline.limit_threads(snakemake.threads)
pipeline.peer_vp(snakemake.input.png, snakemake.input.meta, snakemake.output.json,
                 snakemake.params.peer,
                 pipeline.dataset_focal(snakemake.input.gt, snakemake.input.meta))
