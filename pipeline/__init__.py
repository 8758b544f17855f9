"""Reproducible experiments for measured-reflectance compression and reconstruction."""

from pipeline.cpu import openmp_defaults

openmp_defaults()  # before anything imports torch: libgomp reads its settings once

__version__ = "0.1.0"
