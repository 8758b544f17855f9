"""Method A's data, network and render settings (``btf.*``), each declared once: its
default, what it may be and one line of help. These dataclasses are the structured configs
that ``conf/btf/default.yaml`` extends (Hydra refuses unknown keys and wrong types), the
constraints :func:`pipeline.btf.runner.check_settings_at_the_door` checks, and the roles the
recipe reads (every one changes a result). ``btf.render.*`` has a recipe of its own
(:func:`pipeline.core.recipe.render_recipe_id`); what depends on two of its settings (a crop
inside the frame) is checked by :func:`pipeline.btf.render.stage.render_settings`.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.btf.models import STORAGE_TYPES
from pipeline.core.settings import Either, Integer, ListOf, OneOf, Real, constraints, setting
from pipeline.render.scene import LIGHT_SETTINGS

SEED_BITS = Integer(0, 2**32 - 1)  # scikit-learn's random_state takes 32 bits


@dataclass
class CropSettings:
    """``btf.crop``: the square of texels the chain reads."""

    size: int = setting(100, Integer(1), help="texels per side: M = size² ABRDFs")
    offset: list[int] = setting(
        [0, 0], ListOf(Integer(0), length=2), help="[row, column] of the top-left texel"
    )


@dataclass
class PCASettings:
    """``btf.pca``: the reduction before k-means (clustered only)."""

    n_components: int = setting(16, Integer(1), help="components kept (not given by the paper)")
    random_state: int = setting(
        0, SEED_BITS, help="a PCA setting, not the run's seed: every seed shares one PCA"
    )


@dataclass
class KMeansSettings:
    """``btf.kmeans``: scikit-learn's k-means++ (clustered only; k is ``model.k``)."""

    n_init: int = setting(1, Integer(1), help="restarts")
    max_iter: int = setting(300, Integer(1), help="Lloyd iterations at most")


@dataclass
class NetworkSettings:
    """``btf.network``: the autoencoder (Neural BTF and clustered; the latent texture's
    decoder too)."""

    encoder_channels: list[int] = setting(
        [16, 32, 64],
        ListOf(Integer(1), at_least=1),
        help="one entry per encoder block (conv-pool-BN); not given by the paper",
    )
    latent: int = setting(
        8, Integer(2, 16), help="values per latent (the paper's 8): Neural BTF's size axis"
    )
    hidden: int = setting(106, Integer(1), help="the decoder's width (the paper's 106)")
    layers: int = setting(3, Integer(1), help="the decoder's hidden layers (the paper's 3)")


@dataclass
class SizesSettings:
    """``btf.sizes``: the types Table 1 stores each part in."""

    weight_dtype: str = setting(
        "float32", OneOf(*STORAGE_TYPES), help="decoder weights and latents"
    )
    list_dtype: str = setting(
        "int32", OneOf("int32", "uint16"), help="the cluster list (uint16 for k <= 65536)"
    )
    extra_dtype: str = setting(
        "float32", OneOf(*STORAGE_TYPES), help="the per-texel scale of the graininess fix"
    )


@dataclass
class InterpolationSettings:
    """``btf.interpolation``: directions training never sees."""

    holdout_lights: int = setting(
        0, Integer(0), help="light directions kept out of training, for every view"
    )
    offgrid: int = setting(
        64, Integer(0), help="random off-grid pairs checked against the built-in truth"
    )
    seed: int = setting(0, Integer(0), help="of the held-out lights and off-grid pairs")


# A corner's [row, col], or null: chosen on the truth, else on the reference.
_CORNER = Either(OneOf(None), ListOf(Integer(0), length=2))


@dataclass
class RenderCrops:
    """``btf.render.crops``: the top-left pixel of the dark and the bright crop."""

    dark: list[int] | None = setting(None, _CORNER, help="[row, col]; null: chosen")
    bright: list[int] | None = setting(None, _CORNER, help="[row, col]; null: chosen")


@dataclass
class RenderSettings:
    """``btf.render``: Fig. 8 and Tables 3-4, the crop tiled over a folded sheet
    (:mod:`pipeline.btf.render`). Renders the measured reference, each model and, for the
    built-in material (``dataset.name=synthetic``, ``dataset.root=null``), the analytic
    generator: the truth, which then scores every render (the reference's own distance
    from it logged too). Without a truth, light and view beyond the grid's 75-degree ring
    are clamped onto it for every material alike; the share of samples beyond the grid is
    logged either way."""

    enabled: bool = setting(
        False, OneOf(True, False), help="render after fitting (experiment=render turns it on)"
    )
    width: int = setting(256, Integer(1), help="pixels")
    height: int = setting(256, Integer(1), help="pixels")
    spp: list[int] = setting(
        [1, 16, 128],
        ListOf(Integer(1), at_least=1),
        help="samples per pixel, each rendered; the largest is the headline",
    )
    seed: int = setting(
        0, SEED_BITS, help="pixel samples: one seed for every model, the reference and the truth"
    )
    lights: str = setting(
        "point", OneOf(*LIGHT_SETTINGS), help="pipeline.render.scene.default_scene"
    )
    floor: bool = setting(False, OneOf(True, False), help="a Lambertian floor under the sheet")
    tiles: int = setting(4, Integer(1), help="the crop repeats tiles x tiles times over the sheet")
    mesh_resolution: int = setting(96, Integer(1), help="the sheet's quads per side")
    exposure: float = setting(
        1.0,
        Real(0.0, closed=False),
        help="linear radiance x exposure, then gamma 2.2: the PNGs and the displayed frame "
        "that FLIP, SSIM and PSNR score",
    )
    crop_size: int = setting(32, Integer(1), help="pixels per side of the dark and bright crops")
    crops: RenderCrops = setting(RenderCrops(), help="btf.render.crops.*")


# btf.<group> -> its settings: the structured configs conf/btf/default.yaml extends.
GROUPS = {
    "crop": CropSettings,
    "pca": PCASettings,
    "kmeans": KMeansSettings,
    "network": NetworkSettings,
    "sizes": SizesSettings,
    "interpolation": InterpolationSettings,
    "render": RenderSettings,
}
# Every declared settings class by its prefix, nested ones included.
DECLARED = {**{f"btf.{name}": cls for name, cls in GROUPS.items()}, "btf.render.crops": RenderCrops}


def btf_constraints() -> dict:
    """``{"btf.<group>.<field>": constraint}`` of every declared setting, and ``seed``'s."""
    found = {"seed": SEED_BITS}
    for prefix, settings in DECLARED.items():
        found.update(constraints(settings, prefix))
    return found
