"""Method B: MAP reconstruction of anisotropic BRDFs from measurements with missing angles
(PAPERS.md B).

``microfacet_model`` (the constrained Gaussian-mixture microfacet BRDF) and
``microfacet_em`` (EM with the Dirichlet prior) are the method; ``ashikhmin_shirley`` the
baseline; ``synthetic`` the built-in BRDF; ``runner`` the stages; ``figures`` and
``report`` what a user looks at.
"""
