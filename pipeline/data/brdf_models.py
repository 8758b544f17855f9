"""Analytic BRDF terms that more than one method evaluates: the Ashikhmin-Shirley lobe.

Ashikhmin and Shirley (2000), "An anisotropic Phong BRDF model": the specular lobe of a
surface with normal ``n``, tangent ``t`` and bitangent ``b`` at half vector ``h`` is

    sqrt((n_u + 1)(n_v + 1)) / (8 pi) * (n.h)^((n_u (t.h)^2 + n_v (b.h)^2) / (1 - (n.h)^2))

times Fresnel over ``(k.h) max(n.k1, n.k2)``. Method A's synthetic fabrics
(:mod:`pipeline.btf.synthetic`) shade every texel with it; method B's parametric baseline
(:func:`pipeline.brdf_map.microfacet_model.ashikhmin_shirley_brdf`) fits it. It lives here
because methods do not import each other; the Fresnel term and the denominator's floor
differ between the callers and stay with them.
"""

from __future__ import annotations

import numpy as np

# Below this squared tangential length the half vector is the normal, where the exponent's
# 0/0 has no limit and the lobe is 1 whatever exponent is used.
_TANGENTIAL_FLOOR = 1e-12
# Keeps the logarithm finite where n.h <= 0; those values are set to 0 afterwards.
_LOG_FLOOR = 1e-12


def ashikhmin_shirley_normalization(n_u, n_v):
    """The lobe's normalization ``sqrt((n_u + 1)(n_v + 1)) / (8 pi)`` for Phong exponents
    ``n_u``, ``n_v`` along the tangent and the bitangent (floats or broadcastable arrays)."""
    return np.sqrt((n_u + 1.0) * (n_v + 1.0)) / (8.0 * np.pi)


def ashikhmin_shirley_lobe(n_dot_h, t_dot_h, b_dot_h, n_u, n_v) -> np.ndarray:
    """Unnormalized Ashikhmin-Shirley lobe ``(n.h)^((n_u (t.h)^2 + n_v (b.h)^2) / (1 - (n.h)^2))``.

    In an orthonormal frame ``1 - (n.h)^2 = (t.h)^2 + (b.h)^2``, the form used here: it
    stays finite at ``h = n``, where the lobe is 1. The power is taken as
    ``exp(exponent * log(n.h))`` and is 0 where ``n.h <= 0`` (a half vector below the
    surface). The dtype of the inputs is kept (float32 inputs give float32).

    Parameters
    ----------
    n_dot_h, t_dot_h, b_dot_h : ndarray, broadcastable
        Components of the unit half vector along the normal, the tangent (the ``n_u``
        axis) and the bitangent (the ``n_v`` axis).
    n_u, n_v : float or ndarray, broadcastable with the components
        Phong exponents along the tangent and along the bitangent.

    Returns
    -------
    ndarray of the broadcast shape, in [0, 1]

    Examples
    --------
    Half way between the normal and the tangent, ``(n.h)^n_u``:

    >>> c = np.sqrt(0.5)
    >>> float(ashikhmin_shirley_lobe(np.array(c), np.array(c), np.array(0.0), 4.0, 100.0))
    0.25000000000000006
    """
    tangential = t_dot_h**2 + b_dot_h**2
    exponent = (n_u * t_dot_h**2 + n_v * b_dot_h**2) / np.maximum(tangential, _TANGENTIAL_FLOOR)
    exponent = np.where(tangential > _TANGENTIAL_FLOOR, exponent, n_u)
    lobe = np.exp(exponent * np.log(np.maximum(n_dot_h, _LOG_FLOOR)))
    return np.where(n_dot_h > 0, lobe, 0.0)
