"""Method C: a Fourier-series reflectance model from fixed-camera, moving-light image
stacks, with region segmentation, image quilting and blended optical patterns
(PAPERS.md C).

``series`` is the per-pixel fit (eq. 16-19); ``baselines`` PTM and HSH; ``segmentation``,
``quilting`` and ``optical_pattern`` the texture steps; ``synthetic`` the built-in pot;
``runner`` and ``pattern_runner`` the stages; ``report`` Fig. 6 and the tables.
"""
