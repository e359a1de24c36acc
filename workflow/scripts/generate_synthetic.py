"""Snakemake adapter: generate the synthetic benchmark (rescu.data.synth)."""
from pathlib import Path

from rescu.sections import section_params
from rescu.data.synth import generate_dataset
from rescu.pipeline import setup_logging

setup_logging(snakemake.log[0])
generate_dataset(Path(snakemake.output.annotations).parent,
                 section_params("synthetic", snakemake.params.synth))
