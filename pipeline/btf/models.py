"""Method A's model group: ``model=neural_btf|clustered|pca|latent_texture``.

Each model is a typed, closed config (a dataclass that Hydra stores as the structured
config its ``conf/model/<name>.yaml`` extends: an unknown key such as
``model.n_components`` under ``model=clustered`` is refused) and a :class:`Model` beside
it that says what the chain and the tables need of it. The model is chosen once, here:
code asks the :class:`Model` (``model_of(cfg).clusters``), never compares names.

Light on purpose (no torch): composing a config registers these dataclasses.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from omegaconf import DictConfig

from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, OneOf, Real, setting

STORAGE_TYPES = ("float32", "float16")


@dataclass
class NeuralBTFConfig:
    """The Neural BTF (Rainer et al. 2019): the encoder sees each texel's own ABRDF; one
    latent per texel."""

    name: str = setting("neural_btf", help="the model (fixed by its config file)")
    lr: float = setting(
        0.05,
        Real(0.0, closed=False),
        help="SGD learning rate when train.lr is null (the paper's 0.05)",
    )


@dataclass
class ClusteredConfig:
    """Clustered Neural BTF: the encoder sees the median ABRDF of the texel's k-means
    cluster; one latent per cluster plus the list of cluster ids."""

    name: str = setting("clustered", help="the model (fixed by its config file)")
    k: int = setting(1000, Integer(1), help="k-means clusters: one latent each")
    lr: float = setting(
        0.08,
        Real(0.0, closed=False),
        help="SGD learning rate when train.lr is null (the paper's 0.08)",
    )
    target: str = setting(
        "texel",
        OneOf("texel", "representative"),
        help="train against each texel's own values or its cluster's median",
    )
    texel_scale: str = setting(
        "none",
        OneOf("none", "lstsq", "luminance"),
        help="graininess fix: none, lstsq (per-texel factor) or luminance (mean ratio)",
    )


@dataclass
class PCAConfig:
    """The linear comparator: truncated SVD of the normalised ABRDF matrix, each texel a
    mean ABRDF plus ``n_components`` basis ABRDFs."""

    name: str = setting("pca", help="the model (fixed by its config file)")
    n_components: int = setting(8, Integer(1), help="basis ABRDFs kept")
    dtype: str = setting(
        "float32", OneOf(*STORAGE_TYPES), help="stored type of mean, basis and coefficients"
    )
    match_clustered_k: int | None = setting(
        None,
        Integer(1, optional=True),
        help="an int k: choose n_components to fit the bytes of clustered k",
    )


@dataclass
class LatentTextureConfig:
    """A NeuMIP-style latent texture (Kuznetsov et al. 2021, without its parallax offset):
    per-texel latents optimised directly with the decoder, no encoder
    (:mod:`pipeline.btf.latent_texture`). Latent size and decoder are ``btf.network.*``,
    as for Neural BTF, so both land on the same byte budgets."""

    name: str = setting("latent_texture", help="the model (fixed by its config file)")
    levels: int = setting(
        1,
        Integer(1),
        help="pyramid levels summed into a texel's latent "
        "(folded into one latent per texel when stored)",
    )
    steps: int = setting(
        15000, Integer(1), help="Adam steps; the cosine schedule stretches with them"
    )
    batch_texels: int = setting(64, Integer(1), help="texels per step")
    queries_per_texel: int = setting(64, Integer(1), help="training directions per texel and step")
    lr: float = setting(0.01, Real(0.0, closed=False), help="peak Adam learning rate")


@dataclass(frozen=True)
class Model:
    """What method A's chain and tables need of one model.

    name : ``model.name`` (its config file's name).
    config : its typed config (:func:`pipeline.core.settings.setting` fields).
    title : how a sentence names it.
    stage : ``"module:function"`` of its train stage, whose entry holds ``decoder.pt`` and
        the stored latents for the evaluate and export stages; None: the linear chain.
    size : ``(column, prefix)``: the column of a run (``mlflow.search_runs``) that is its
        size axis in the rate-distortion figures, and that axis' label (``k = 500``).
    size_settings : the settings (flattened keys) that set its size: a rate-distortion
        line varies them, so they are left out of the comparison of its recipes.
    column : ``(run) -> str``, its Table 2 column from a run (a row of
        ``mlflow.search_runs``: ``params.*`` strings and ``metrics.*``).
    trains : it trains the autoencoder, so ``train.*`` makes its numbers.
    clusters : it runs the reduction, k-means and representatives stages.
    rank : where its columns go in a table (then by size).
    stored_types : ``(run) -> str``, the types its parts are stored in (``float16, list
        uint16``), from a run's ``params.*``.
    """

    name: str
    config: type
    title: str
    stage: str | None
    size: tuple[str, str]
    size_settings: tuple[str, ...]
    column: Callable[[Mapping], str] = field(repr=False)
    trains: bool
    clusters: bool
    rank: int = 0
    stored_types: Callable[[Mapping], str] = field(repr=False, default=lambda run: "")

    def run_name(self, cfg: DictConfig) -> str:
        k = f" k={cfg.model.k}" if self.clusters else ""
        return f"{self.name}{k} s{cfg.seed}"

    def unused(self, cfg: DictConfig) -> list[str]:
        """Flattened settings this model's numbers do not depend on: not logged, not in
        the recipe. ``model.lr`` is only the default of ``train.lr`` (which the job
        resolves and logs); a model that trains nothing reads no ``train.*``, one that
        does not cluster none of the clustering stages' :data:`CLUSTERING` settings."""
        unused = ["model.lr"] if self.trains else [f"train.{key}" for key in cfg.train]
        if not self.clusters:
            unused += [f"btf.{group}.{key}" for group in CLUSTERING for key in cfg.btf[group]]
        return unused


TRAIN = "pipeline.btf.runner:train_stage"  # the autoencoder's
# The settings groups under btf.* that only the reduction and k-means stages read.
CLUSTERING = ("pca", "kmeans")


def _param(run: Mapping, key: str, default: str) -> str:
    value = run.get(f"params.{key}")
    return default if value is None or value != value else str(value)  # NaN: not logged


def _weight_type(run: Mapping) -> str:
    return _param(run, "btf.sizes.weight_dtype", "float32")


def _clustered_types(run: Mapping) -> str:
    types = f"{_weight_type(run)}, list {_param(run, 'btf.sizes.list_dtype', 'int32')}"
    if _param(run, "model.texel_scale", "none") != "none":
        types += f", +scale {_param(run, 'btf.sizes.extra_dtype', 'float32')}"
    return types


def _int_text(value) -> str:
    try:
        return str(int(float(value)))
    except (TypeError, ValueError):
        return "?"


def _pca_column(run: Mapping) -> str:
    """``PCA c = <c>``, and ``(over budget)`` where the budget it was given held no component
    and it ran with one (the run's ``over_budget`` tag)."""
    column = "PCA c = " + _int_text(run.get("metrics.n_components"))
    return column + " (over budget)" if isinstance(run.get("tags.over_budget"), str) else column


MODELS: dict[str, Model] = {
    model.name: model
    for model in (
        Model(
            "neural_btf",
            NeuralBTFConfig,
            "Neural BTF",
            TRAIN,
            trains=True,
            clusters=False,
            size=("params.btf.network.latent", "latent "),
            size_settings=("btf.network.latent",),
            column=lambda run: "Neural BTF",
            stored_types=_weight_type,
        ),
        Model(
            "clustered",
            ClusteredConfig,
            "clustered",
            TRAIN,
            trains=True,
            clusters=True,
            size=("params.model.k", "k = "),
            size_settings=("model.k",),
            column=lambda run: "k = " + _int_text(run.get("params.model.k")),
            rank=2,
            stored_types=_clustered_types,
        ),
        Model(
            "pca",
            PCAConfig,
            "PCA",
            None,
            trains=False,
            clusters=False,
            size=("metrics.n_components", "c = "),
            size_settings=("model.n_components", "model.match_clustered_k"),
            column=_pca_column,
            rank=3,
            stored_types=lambda run: _param(run, "model.dtype", "float32"),
        ),
        Model(
            "latent_texture",
            LatentTextureConfig,
            "latent texture",
            "pipeline.btf.latent_stage:train_stage",
            trains=False,
            clusters=False,
            size=("params.btf.network.latent", "latent "),
            size_settings=("btf.network.latent",),
            column=lambda run: "latent texture",
            rank=1,
            stored_types=_weight_type,
        ),
    )
}


def model_of(cfg: DictConfig) -> Model:
    """The :class:`Model` the composed config's ``model.name`` names."""
    name = cfg.model.get("name") if cfg.get("model") is not None else None
    if name not in MODELS:
        raise ConfigError(
            f"model.name={name!r} is not a model of method A: choose model={'|'.join(MODELS)}"
        )
    return MODELS[name]


def models_of(runs) -> list[Model | None]:
    """The :class:`Model` of each run (rows of ``mlflow.search_runs``), None for runs of
    other methods."""
    names = runs["params.model.name"] if "params.model.name" in runs else [None] * len(runs)
    return [MODELS.get(name) for name in names]


def schemas() -> tuple[tuple[str, str, type], ...]:
    """The structured configs the ``conf/model/*.yaml`` files extend."""
    return tuple(("schema/model", name, model.config) for name, model in MODELS.items())
