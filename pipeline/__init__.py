"""Reproducible experiments for measured-reflectance compression and reconstruction."""

__version__ = "0.1.0"
