"""Snakemake adapter: generate the synthetic benchmark (rescu.data.synth)."""
from pathlib import Path

from rescu.pipeline import setup_logging
from rescu.data.synth import SynthParams, generate_dataset

setup_logging(snakemake.log[0])
generate_dataset(Path(snakemake.output.annotations).parent, SynthParams.from_dict(snakemake.params.synth))
