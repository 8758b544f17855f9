"""Method A's renders: Fig. 8 and Tables 3-4 of the clustering paper, on the general
renderer :mod:`pipeline.render`.

- :mod:`~pipeline.btf.render.surfaces`: A's materials (the measured BTF and the PCA
  baseline interpolated between the 81 x 81 directions, a compressed BTF file, the built-in
  material's generator) and the rule for directions beyond the measured grid.
- :mod:`~pipeline.btf.render.stage`: the cached render stages and their scores.
- :mod:`~pipeline.btf.render.report`: Fig. 8 and Tables 3-4 from the MLflow runs.

``python -m benchmarks.render`` measures the cost of a frame per material.

Nothing is imported here, so importing a submodule does not load Embree or torch.
"""

# The ``method.name`` of the jobs rendered when ``btf.render.enabled``: method A.
RENDERED = ("btf",)
