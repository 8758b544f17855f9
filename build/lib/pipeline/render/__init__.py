"""A small renderer of a textured cloth (the paper's Fig. 8 scene), on Embree via ``embreex``.

- :mod:`pipeline.render.scene`: triangle meshes with uv and tangent frames, a pinhole
  camera, point and directional lights; :func:`~pipeline.render.scene.folded_sheet` and
  :func:`~pipeline.render.scene.default_scene` build the draped cloth.
- :mod:`pipeline.render.materials`: what a surface point reflects, queried in batches:
  the :class:`~pipeline.render.materials.Material` interface and a Lambertian texture
  (closed form, for tests).
- :mod:`pipeline.render.engine`: :func:`~pipeline.render.engine.render`, direct lighting
  with hard shadows and jittered samples per pixel; the conventions (directions, uv to
  texel, units) are in its docstring.

A library below the methods: it imports no method package (``tests/test_imports.py``
checks it). A method's materials, render stages and reports live in its own package
(method A's in :mod:`pipeline.btf.render`).

Nothing is imported here, so importing a submodule does not load Embree.
"""
