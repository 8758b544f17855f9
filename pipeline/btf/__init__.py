"""Method A: Neural BTF compression with clustering (PAPERS.md A).

``stages`` (load, crop, preprocess, pca, kmeans, representatives) and ``runner`` (train,
evaluate, the PCA baseline) are the chain; ``preprocess``, ``clustering``, ``model``,
``train``, ``evaluate``, ``interpolation``, ``linear`` and ``stereographic`` its pure
functions; ``synthetic`` the built-in woven BTF; ``report`` (with ``tables``, ``curves``,
``fig7``) the tables and figures; ``fast`` the fused training step, its C++ kernels and
the opt-in machine tuning.
"""
