"""A small BTF renderer for the paper's cloth figure (Fig. 8), on Embree via ``embreex``.

- :mod:`pipeline.render.scene`: triangle meshes with uv and tangent frames, a pinhole
  camera, point and directional lights; :func:`~pipeline.render.scene.folded_sheet` and
  :func:`~pipeline.render.scene.default_scene` build the draped cloth.
- :mod:`pipeline.render.materials`: what a surface point reflects, queried in batches:
  a Lambertian texture (closed form, for tests), the measured BTF interpolated between its
  81 x 81 directions (the reference), the PCA baseline interpolated the same way, and a
  compressed BTF file.
- :mod:`pipeline.render.engine`: :func:`~pipeline.render.engine.render`, direct lighting
  with hard shadows and jittered samples per pixel; the conventions (directions, uv to
  texel, units) are in its docstring.

- :mod:`pipeline.render.stage` and :mod:`pipeline.render.report`: the cached render
  stages of method A and Fig. 8 / Tables 3-4.

Nothing is imported here, so importing a submodule does not load Embree or torch.
"""

# The ``method.name`` of the jobs rendered when ``btf.render.enabled``: method A's models.
RENDERED = ("neural_btf", "clustered", "pca")
