"""Method A's model group (pipeline/btf/models.py) and the sweeps that compose exactly what
the command line says (pipeline/core/sweeper.py): each setting declared once, with its role,
and everything else derived from that declaration."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest
from helpers import PACKAGE, compose_config
from omegaconf import OmegaConf

from pipeline.btf.methods import BTF, unused
from pipeline.btf.models import MODELS, model_of
from pipeline.btf.runner import SPEED_ONLY, keyless
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.recipe import left_out, recipe_id
from pipeline.core.run import flatten
from pipeline.core.settings import RESULT, added_defaults, roles, setting
from pipeline.core.sweeper import expand


def _jobs(*command_line: str) -> list[list[str]]:
    """The jobs ``python -m pipeline -m <command_line>`` launches (what the arms sweeper
    computes from the composed ``hydra.sweeper``), each composed as Hydra validates it."""
    experiment = [o for o in command_line if o.startswith("experiment=")]
    given = [o for o in command_line if not o.startswith("experiment=")]
    sweeper = compose_config(*experiment, return_hydra_config=True).hydra.sweeper
    arms = OmegaConf.to_container(sweeper.arms) if sweeper.get("arms") else None
    params = OmegaConf.to_container(sweeper.params) if sweeper.get("params") else None
    return [experiment + job for job in expand(arms, params, given)]


def test_a_k_by_seed_sweep_composes_nine_jobs_not_twenty_seven():
    """The issue's sweep: the default experiment's three arms are replaced by the command
    line's model, never crossed with it."""
    jobs = _jobs("model=clustered", "model.k=500,1000,2000", "seed=0,1,2")
    assert len(jobs) == 9
    found = set()
    for job in jobs:
        cfg = compose_config(*job)
        assert cfg.model.name == "clustered" and set(cfg.model) == {
            "name",
            "k",
            "lr",
            "target",
            "texel_scale",
        }
        found.add((cfg.model.k, cfg.seed))
    assert found == {(k, s) for k in (500, 1000, 2000) for s in (0, 1, 2)}


def test_the_sweeps_parent_run_logs_the_settings_its_jobs_set():
    """The parent run's params are the launched jobs' settings (arms, axes and command
    line), each with its values in job order: the default experiment's arms too."""
    from pipeline.core.sweep_run import swept_settings

    hydra = compose_config(return_hydra_config=True).hydra
    config = OmegaConf.create({"hydra": {"sweeper": hydra.sweeper, "overrides": {"task": []}}})
    swept = swept_settings(config)
    assert swept["model"] == ",".join(str(arm["model"]) for arm in hydra.sweeper.arms)
    config.hydra.overrides.task = ["model=clustered", "model.k=500,1000,2000", "seed=0,1,2"]
    assert swept_settings(config) == {
        "model": "clustered",
        "model.k": "500,1000,2000",
        "seed": "0,1,2",
    }


def test_the_sweep_says_how_many_arms_the_command_line_keeps():
    """An arm whose every key the command line replaces is kept (1 of 3), and a model no
    arm has keeps none (0 of 3)."""
    sweeper = compose_config(return_hydra_config=True).hydra.sweeper
    arms = OmegaConf.to_container(sweeper.arms)
    said: list[str] = []
    expand(arms, None, ["model=clustered", "model.k=2000"], announce=said.append)
    expand(arms, None, ["model=latent_texture"], announce=said.append)
    assert said == [
        "model=clustered on the command line keeps 1 of the experiment's 3 arms",
        "model=latent_texture on the command line keeps 0 of the experiment's 3 arms",
    ]


def test_arms_the_command_line_makes_identical_launch_each_job_once():
    """experiment=rate_distortion has three PCA arms (float32, float16, and 32/64
    components); a command line that replaces their size and storage type launches each
    of its jobs once, not three times."""
    command = ["model=pca", "model.n_components=16,32", "model.dtype=float16"]
    jobs = _jobs("experiment=rate_distortion", *command)
    assert sorted(sorted(job) for job in jobs) == [
        sorted(["experiment=rate_distortion", "model=pca", f"model.n_components={c}", command[2]])
        for c in (16, 32)
    ]
    said: list[str] = []
    arms = [{"m": "a", "m.n": "1,2"}, {"m": "a", "m.n": "3"}, {"m": "b"}]
    assert expand(arms, None, ["m=a", "m.n=4"], announce=said.append) == [["m=a", "m.n=4"]]
    assert said == ["m=a on the command line keeps 1 of the experiment's 3 arms"]


def test_the_default_and_paper_experiments_compose_their_arms():
    default = [compose_config(*job).model for job in _jobs()]
    assert [m.name for m in default] == ["neural_btf", "clustered", "pca"]
    assert default[1].k == 128 and default[2].match_clustered_k == 128
    assert default[2].dtype == "float16"
    paper = [compose_config(*job).model for job in _jobs("experiment=paper", "seed=0,1")]
    assert len(paper) == 10 and sorted(m.k for m in paper if m.name == "clustered") == [
        500,
        500,
        1000,
        1000,
        2000,
        2000,
    ]
    # PCA at the bytes of k = 1000 in float16: in float32 not one component fits them.
    assert {(m.dtype, m.match_clustered_k) for m in paper if m.name == "pca"} == {("float16", 1000)}
    # A command-line value replaces the arm's: k = 64 in the clustered arm only.
    jobs = _jobs("experiment=paper", "model=clustered", "model.k=64")
    assert [compose_config(*job).model.k for job in jobs] == [64]


def test_a_setting_of_another_model_is_refused_naming_it():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="model.n_components"):
        compose_config("model=clustered", "model.n_components=8")
    with pytest.raises(ConfigCompositionException, match="model.k"):
        compose_config("model=neural_btf", "model.k=8")


def test_an_experiment_sets_a_models_own_settings_only_for_that_model():
    """experiment=smoke's k = 8 (conf/experiment_model/smoke_clustered.yaml) applies to the
    clustered model, and the command line still wins."""
    assert compose_config("experiment=smoke").model.k == 8
    assert compose_config("experiment=smoke", "model.k=4").model.k == 4
    assert "k" not in compose_config("experiment=smoke", "model=neural_btf").model
    assert compose_config("experiment=render_smoke").model.k == 8


def test_every_setting_declares_its_role():
    for model in MODELS.values():
        assert set(roles(model.config, "model").values()) <= {"result", "speed", "log"}
    assert roles(TrainSettings, "train")["train.threads"] == "speed"

    @dataclasses.dataclass
    class Undeclared:
        size: int = setting(1)
        other: int = 2

    with pytest.raises(TypeError, match="Undeclared.other has no role"):
        roles(Undeclared, "x")


def test_every_setting_of_method_a_is_declared_once_with_a_role():
    """Every leaf of a method-A job's btf.*, train.* and model.* is a declared field with a
    role, and the config's defaults are the declaration's: conf/btf/default.yaml holds no
    value of its own for them."""
    from pipeline.btf.data_settings import DECLARED

    cfg = compose_config("experiment=none", "model=clustered")
    declared = BTF.roles()
    leaves = {
        key
        for key in flatten(cfg)
        if key.startswith(("btf.", "train.", "model.")) and key != "model.name"
    }
    assert leaves <= set(declared), sorted(leaves - set(declared))
    assert {"btf.render.spp", "btf.render.crops.dark"} <= leaves
    for prefix, settings in DECLARED.items():
        for f in dataclasses.fields(settings):
            default = f.default_factory() if f.default is dataclasses.MISSING else f.default
            if not dataclasses.is_dataclass(default):  # nested: checked under its own prefix
                value = OmegaConf.select(cfg, f"{prefix}.{f.name}")
                assert value == default, f"{prefix}.{f.name}"


@pytest.mark.parametrize("name", list(MODELS))
def test_keys_recipe_and_logged_settings_follow_from_the_declaration(name):
    """For each model, from the one declaration (field roles): the train stage's key holds
    no speed setting, the recipe holds exactly the result settings, and the logged
    settings leave out what the model does not read."""
    cfg = compose_config("experiment=smoke", f"model={name}")
    model = model_of(cfg)
    declared = {**roles(TrainSettings, "train"), **roles(model.config, "model")}
    for key, role in declared.items():
        assert left_out(key) == (role != RESULT), key
    assert SPEED_ONLY == {k.removeprefix("train.") for k, r in declared.items() if r == "speed"}
    logged = set(flatten(cfg)) - set(unused(cfg))
    assert {f"model.{f.name}" for f in dataclasses.fields(model.config)} - {"model.lr"} <= logged
    assert ("train.epochs" in logged) == model.trains
    assert ("btf.kmeans.n_init" in logged) == ("btf.pca.n_components" in logged) == model.clusters
    # A model trained by train.* logs the train.lr it trains at, not its default model.lr.
    assert ("model.lr" in logged) == (not model.trains and "lr" in model.config.__annotations__)
    assert BTF.roles()["train.device"] == "speed"


def test_an_added_setting_at_its_default_leaves_keys_recipe_and_logged_settings_as_before():
    """train.clip_grad_norm came after results existed (declared ``added``): at its
    default (None) it is in no train-stage key, recipe or logged setting, so those results
    stay the same models; set, it is in all three."""
    assert "train.clip_grad_norm" in added_defaults(TrainSettings, "train")
    plain = compose_config("experiment=smoke", "model=neural_btf")
    clipped = compose_config("experiment=smoke", "model=neural_btf", "train.clip_grad_norm=1.0")
    assert "train.clip_grad_norm" in BTF.left_out(plain)
    assert "train.clip_grad_norm" not in BTF.left_out(clipped)
    assert "clip_grad_norm" in keyless(TrainSettings())
    assert "clip_grad_norm" not in keyless(TrainSettings(clip_grad_norm=1.0))

    # The rule leaves out the added setting at its default and nothing else: the job logs
    # (and its recipe hashes) what it logged before the setting existed.
    assert set(BTF.left_out(plain)) - set(unused(plain)) == {"train.clip_grad_norm"}

    def logged(cfg):
        return {k: v for k, v in flatten(cfg).items() if k not in set(BTF.left_out(cfg))}

    assert logged(clipped)["train.clip_grad_norm"] == 1.0
    assert recipe_id(logged(clipped)) != recipe_id(logged(plain))
    with pytest.raises(ValueError, match="plain default"):
        setting([1], added=True)


def test_no_model_is_chosen_by_comparing_names():
    """No comparison in the package's code (docstrings aside) has a model's name on either
    side, however the name was read (``cfg.model.name``, a run's ``params.model.name``)."""
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                if any(isinstance(n, ast.Constant) and n.value in MODELS for n in sides):
                    found.append(f"{path}:{node.lineno}")
    assert found == []


def test_the_latent_texture_model_runs_through_the_chain(smoke_cfg, own_cache):
    """``model=latent_texture`` (NeuMIP-style, no encoder) through the job: its file's
    payload is its bytes_total, the file's numpy reader equals the torch decoder on the
    stored latents, and it ends far below the mean-ABRDF baseline."""
    import numpy as np
    import torch
    from mlflow.tracking import MlflowClient

    from pipeline.app import run_job
    from pipeline.btf.compressed import FILE_NAME, load_compressed, payload_bytes
    from pipeline.btf.model import load_decoder
    from pipeline.btf.stereographic import direction_features
    from pipeline.core.store import tracking_uri

    cfg = smoke_cfg(own_cache, "model=latent_texture")
    run_job(cfg)
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    [run] = client.search_runs([client.get_experiment_by_name("smoke").experiment_id])
    metrics = run.data.metrics
    assert run.data.params["model.name"] == "latent_texture" and "train.lr" not in run.data.params
    assert metrics["rmse"] < 0.5 * metrics["rmse_mean_abrdf"]
    cache = Path(cfg.paths.cache)
    [path] = (cache / "export").glob(f"*/{FILE_NAME}")
    assert payload_bytes(path) == metrics["bytes_total"]
    [trained] = (cache / "train").glob("*/")
    # Its Fig. 7 is logged, as every trained model's: the tables draw it from the run.
    from pipeline.btf.fig7 import logged_data

    fig7 = logged_data(run.info.run_id)
    assert fig7 is not None and fig7["model"].shape == fig7["reference"].shape
    decoder = load_decoder(trained / "decoder.pt")
    latents = np.load(trained / "latents.npy")
    compressed = load_compressed(path)
    rng = np.random.default_rng(0)
    texels = rng.integers(0, latents.shape[0], 50)
    directions = np.column_stack(
        [
            rng.uniform(0, 1.3, 50),
            rng.uniform(-3, 3, 50),
            rng.uniform(0, 1.3, 50),
            rng.uniform(-3, 3, 50),
        ]
    )
    with torch.no_grad():
        expected = decoder(
            torch.from_numpy(latents[texels]),
            torch.from_numpy(direction_features(directions)).float(),
        ).numpy()
    np.testing.assert_allclose(
        compressed.query_pairs(texels, directions),
        expected * compressed.alpha,
        rtol=1e-4,
        atol=1e-6,
    )
