"""Reproducible experiments for measured-reflectance compression and reconstruction.

One subpackage per method: :mod:`pipeline.btf` (A, Neural BTF with clustering),
:mod:`pipeline.brdf_map` (B, MAP reconstruction of anisotropic BRDFs) and
:mod:`pipeline.fourier` (C, Fourier-series light stacks); :mod:`pipeline.core` holds what
they share and :mod:`pipeline.data` the readers of real file layouts. Importing any of them
changes nothing outside the module.
"""

__version__ = "0.1.0"
