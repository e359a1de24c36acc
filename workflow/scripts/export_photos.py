"""Snakemake adapter: copy the package-shipped photos into the photos dataset."""
from pathlib import Path

from rescu.data.photos import export_package_photos
from rescu.pipeline import setup_logging

setup_logging(snakemake.log[0])
export_package_photos(snakemake.params.names, Path(snakemake.output.images[0]).parent.parent)
