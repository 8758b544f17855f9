"""Bad settings are refused before any stage runs, with a message naming the setting and
what it may be (issue: "bad settings not refused, or refused late")."""

from pathlib import Path

import pytest

from pipeline.app import run_job
from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, ListOf, OneOf, Real, check_settings

# train.* is a structured config (pipeline.btf.train_settings.TrainSettings): Hydra refuses
# a value of the wrong type as it composes, naming the key.
BAD_TYPES = [
    "train.lr=abc",
    "train.epochs=nan",
    "train.batch_size=nan",
    "train.queries_per_abrdf=nan",
    "train.epoch_texels=nan",
    "train.epochs=1.5",
    "train.epochs=true",
    "model.k=true",
    "model.k=1.5",
]
BAD = [
    ("train.lr=nan", "train.lr=nan must be a finite number"),
    ("train.lr=-1", "train.lr=-1.0 must be a finite number > 0"),
    ("train.batch_size=1", "train.batch_size=1 must be an integer >= 2"),
    ("btf.sizes.weight_dtype=foo", "btf.sizes.weight_dtype='foo' must be one of float32, float16"),
    ("model.k=0", "model.k=0 must be an integer >= 1"),
    ("model.texel_scale=both", "model.texel_scale='both' must be one of none, lstsq, luminance"),
    ("btf.kmeans.n_init=0", "btf.kmeans.n_init=0 must be an integer >= 1"),
    ("seed=5000000000", "seed=5000000000 must be an integer >= 0 and <= 4294967295"),
    ("btf.crop.offset=[0]", "btf.crop.offset=[0] must be a list of 2 items"),
]


@pytest.mark.parametrize(("override", "message"), BAD)
def test_a_bad_setting_is_refused_before_any_stage(
    smoke_cfg, own_cache, tmp_path, override, message
):
    cfg = smoke_cfg(own_cache, f"paths.data={tmp_path / 'data'}", override)
    with pytest.raises(ConfigError) as error:
        run_job(cfg)
    assert message in str(error.value)
    cache = Path(cfg.paths.cache)
    assert not cache.exists() or not [p for p in cache.glob("*/*") if not p.name.startswith(".")]
    assert not Path(cfg.paths.data).exists()  # the built-in data was not even generated


@pytest.mark.parametrize("override", BAD_TYPES)
def test_a_value_of_the_wrong_type_is_refused_as_the_config_is_composed(smoke_cfg, override):
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException) as error:
        smoke_cfg(override)
    assert f"full_key: {override.split('=')[0]}" in str(error.value.__cause__ or error.value)


def test_a_setting_of_another_model_is_refused_as_the_config_is_composed(smoke_cfg):
    """Each model's config is closed: ``model.n_components`` is PCA's, not clustered's."""
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="model.n_components"):
        smoke_cfg("model=clustered", "model.n_components=8")


def test_the_pca_arm_checks_its_own_settings(smoke_cfg):
    with pytest.raises(ConfigError, match="model.dtype='float64' must be one of"):
        run_job(smoke_cfg("model=pca", "model.dtype=float64"))


@pytest.mark.parametrize(
    ("constraint", "good", "bad"),
    [
        (Integer(1), [1, 10**12], [0, 1.0, True, None, "1", float("nan")]),
        (Integer(0, 3, optional=True), [0, 3, None], [4, -1, 2.5]),
        (
            Real(0.0, closed=False),
            [1e-9, 2, 0.5],
            [0, 0.0, -1, float("inf"), float("nan"), True, "1"],
        ),
        (Real(0.0, high=100.0), [0, 5.0, 100], [100.5, -1e-9, float("nan"), None]),
        (OneOf("a", None), ["a", None], ["b", 0, False]),
        (ListOf(Integer(0), length=2), [[0, 1], (2, 3)], [[0], [0, -1], "01", [0, 1.5]]),
    ],
)
def test_constraints_by_hand(constraint, good, bad):
    for value in good:
        check_settings({"x": value}, {"x": constraint})
    for value in bad:
        with pytest.raises(ConfigError, match=r"^x="):
            check_settings({"x": value}, {"x": constraint})
