"""The reflectance of the built-in fabric (:class:`pipeline.btf.synthetic.SyntheticBTF`).

Given per-texel frames (normal, fibre tangent, bitangent), a depth, an albedo and the
preset's yarn constants, :func:`texel_maps` lays out the per-texel parameters of the
shading, and :func:`shade` evaluates it at light/view directions. Both are pure functions
of arrays; the fabric's geometry comes from :mod:`pipeline.btf.synthetic`.

Image value for light l and view v (both unit vectors, z = macro normal)::

    exposure · max(n·l, 0) · S(l) · M(v) · (albedo / π + k_s · AS(l, v))

with ``AS`` an Ashikhmin–Shirley anisotropic specular lobe aligned with the fibre tangent,
and smooth self-shadowing ``S(l) = exp(-k · depth · tan θ_l · a(φ_l))``: deep texels
darken at grazing light, and ``a`` grows for light crossing the fibre's channel rather
than running along it; the same masking ``M(v)``, times a fade where the local surface
turns from the view. Values are clipped to [0, 1]; directions below the horizon give 0.
"""

from __future__ import annotations

import numpy as np

from pipeline.btf.materials import Material, Surface
from pipeline.data.brdf_models import ashikhmin_shirley_lobe, ashikhmin_shirley_normalization
from pipeline.data.directions import unit_vectors

# Shadowing features of a direction: tan θ · (1, |sin(φ - β)| for each channel azimuth β).
# Light that crosses a channel running at β is shadowed by its walls, light along it is
# not. 0° and 90° (the plain weave's threads) come first; the diagonals serve fibres at
# other angles, whose weight is shared between the two nearest channels.
_CHANNEL_DEGREES = np.array([0.0, 90.0, 30.0, 60.0, 120.0, 150.0])
_CHANNEL_STEP = 30.0


def channel_weights(fibre: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Weights of the channel features, (len(_CHANNEL_DEGREES), P), for in-plane fibre
    directions ``fibre`` (P, 2) at any azimuth (any length but zero): ``across`` (P,), how
    strongly each texel shadows light crossing its fibre, shared between the two channels
    nearest the fibre's azimuth, linearly in angle (all of it on one channel when the fibre
    runs along one)."""
    azimuth = np.mod(np.degrees(np.arctan2(fibre[:, 1], fibre[:, 0])), 180.0)
    position = azimuth / _CHANNEL_STEP
    lower = np.floor(position)
    share = position - lower
    # The channels in order of azimuth (0°, 30°, …, 150°), as rows of the weights.
    row_of_step = np.argsort(np.round(_CHANNEL_DEGREES / _CHANNEL_STEP))
    below = row_of_step[lower.astype(int) % len(row_of_step)]
    above = row_of_step[(lower.astype(int) + 1) % len(row_of_step)]
    weights = np.zeros((len(_CHANNEL_DEGREES), len(across)))
    texels = np.arange(len(across))
    weights[below, texels] += across * (1 - share)
    weights[above, texels] += across * share
    return weights


def texel_maps(
    preset: Material,
    surface: Surface,
    normal: np.ndarray,
    tangent: np.ndarray,
    bitangent: np.ndarray,
    depth: np.ndarray,
    albedo: np.ndarray,
) -> dict[str, np.ndarray]:
    """The per-texel parameters that :func:`shade` reads, texels flattened (P = S²).

    Parameters
    ----------
    preset : Material, whose yarn constants and shadow strength are used.
    surface : Surface, the preset's geometry (its labels and fibre directions are used).
    normal, tangent, bitangent : ndarray of shape (S, S, 3)
        Unit frame per texel; the tangent runs along the (twisted) fibre.
    depth : ndarray of shape (S, S), 0 on the highest crest, 1 at the lowest floor.
    albedo : ndarray of shape (S, S, 3), diffuse albedo in [0, 1].

    Returns
    -------
    dict of str to float32 ndarray
        ``normal``, ``tangent``, ``bitangent``: (3, P), for matmul; ``occlusion_weights``:
        (1 + channels, P); ``albedo_over_pi``: (P, 3); ``exponent_along``,
        ``exponent_across``, ``specular_scale``: (P,).
    """
    labels = surface.labels.ravel()

    def per_texel(field):  # a Yarn field, looked up by each texel's label
        return np.array([getattr(yarn, field) for yarn in preset.yarns])[labels]

    flat = {
        name: frame.reshape(-1, 3).T.astype(np.float32)  # (3, P) for matmul
        for name, frame in (("normal", normal), ("tangent", tangent), ("bitangent", bitangent))
    }
    # Occlusion exponent = features(direction) @ occlusion_weights (see
    # _CHANNEL_DEGREES): deep texels shadow more, and the walls of a fibre's channel
    # shadow light coming across the fibre more than light along it.
    weights = np.zeros((1 + len(_CHANNEL_DEGREES), labels.size))
    weights[0] = per_texel("shadow")
    weights[1:] = channel_weights(surface.fibre.reshape(-1, 2), per_texel("shadow_across"))
    occlusion_weights = preset.shadow_strength * depth.ravel() * weights
    flat["occlusion_weights"] = occlusion_weights.astype(np.float32)
    flat["albedo_over_pi"] = (albedo.reshape(-1, 3) / np.pi).astype(np.float32)
    along = per_texel("exponent_along")
    across = per_texel("exponent_across")
    flat["exponent_along"] = along.astype(np.float32)
    flat["exponent_across"] = across.astype(np.float32)
    # Ashikhmin–Shirley normalization times the yarn's specular weight.
    specular_scale = per_texel("specular") * ashikhmin_shirley_normalization(along, across)
    flat["specular_scale"] = specular_scale.astype(np.float32)
    return flat


def shade(directions: np.ndarray, maps: dict, preset: Material, pairs: bool) -> np.ndarray:
    """The shading of texels ``maps`` at ``directions``.

    Parameters
    ----------
    directions : ndarray of shape (c, 4), float64, (θ_light, φ_light, θ_view, φ_view) radians.
    maps : dict
        :func:`texel_maps`' arrays, or a selection of their texels (texel axis last;
        ``albedo_over_pi`` first).
    preset : Material, whose exposure and Fresnel reflectance at normal incidence are used.
    pairs : bool, False: every direction at every texel; True: the i-th at the i-th texel

    Returns
    -------
    ndarray of shape (c, P, 3), or (c, 3) with ``pairs``; float32 in [0, 1]
    """

    def per_direction(values):  # (c,) -> broadcast against the texel axis
        return values if pairs else values[:, None]

    def dot(vectors, frames):  # (c, 3) with (3, P): (c, P), or (3, c) pairwise: (c,)
        return np.sum(vectors.T * frames, axis=0) if pairs else vectors @ frames

    theta_light = np.clip(directions[:, 0], 0.0, np.pi)
    theta_view = np.clip(directions[:, 2], 0.0, np.pi)
    light = unit_vectors(theta_light, directions[:, 1]).astype(np.float32)
    view = unit_vectors(theta_view, directions[:, 3]).astype(np.float32)
    halfway = light + view
    halfway /= np.maximum(np.linalg.norm(halfway, axis=1, keepdims=True), 1e-12)
    light_dot_half = per_direction(np.clip(np.sum(light * halfway, axis=1), 1e-4, 1.0))

    n_dot_l = dot(light, maps["normal"])  # (c, P), or (c,) for pairs
    n_dot_v = dot(view, maps["normal"])
    n_dot_h = dot(halfway, maps["normal"])
    t_dot_h = dot(halfway, maps["tangent"])
    b_dot_h = dot(halfway, maps["bitangent"])

    # The fibre tangent is the lobe's n_u axis; the normalization is in specular_scale.
    lobe = ashikhmin_shirley_lobe(
        n_dot_h, t_dot_h, b_dot_h, maps["exponent_along"], maps["exponent_across"]
    )
    fresnel_at_normal = preset.fresnel_at_normal
    fresnel = fresnel_at_normal + (1 - fresnel_at_normal) * (1 - light_dot_half) ** 5
    # The 0.1 floor keeps the lobe finite where a texel turns edge-on to both.
    denominator = light_dot_half * np.maximum(np.maximum(n_dot_l, n_dot_v), 0.1)
    specular = maps["specular_scale"] * lobe * fresnel / denominator

    def occlusion_features(theta, phi):  # (c,) -> (c, 1 + channels)
        tan_theta = np.tan(np.minimum(theta, np.deg2rad(89.0)))
        across = np.abs(np.sin(phi[:, None] - np.deg2rad(_CHANNEL_DEGREES)))
        return tan_theta[:, None] * np.concatenate([np.ones_like(phi)[:, None], across], 1)

    # Shadowing (light) times masking (view): exp(-a_l) exp(-a_v) = exp(-(a_l + a_v)).
    features = occlusion_features(theta_light, directions[:, 1]) + occlusion_features(
        theta_view, directions[:, 3]
    )
    occlusion = np.exp(-dot(features.astype(np.float32), maps["occlusion_weights"]))
    # Fade texels whose local surface turns away from the viewer (seen at a graze).
    facing = np.clip(n_dot_v / 0.2, 0.0, 1.0)
    facing = facing * facing * (3 - 2 * facing)
    above = per_direction((np.cos(theta_light) > 0) & (np.cos(theta_view) > 0))
    exposure = preset.exposure
    weight = np.where(above, exposure * np.maximum(n_dot_l, 0) * occlusion * facing, 0.0)
    values = weight[..., None] * (maps["albedo_over_pi"] + specular[..., None])
    return np.clip(values, 0.0, 1.0).astype(np.float32)
