"""Method A as the job and the tables command see it (:class:`pipeline.core.methods.Method`):
one method whose model (Neural BTF, clustered, PCA) is the ``model`` group
(:mod:`pipeline.btf.models`). Light on purpose: the functions here import the chain when
called."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from pipeline.btf.data_settings import DECLARED, GROUPS
from pipeline.btf.models import MODELS, model_of, schemas
from pipeline.btf.train_settings import TrainSettings
from pipeline.core.methods import Method
from pipeline.core.settings import schema

if TYPE_CHECKING:
    from pipeline.core.stage import Context


def run(ctx: Context) -> dict[str, float]:
    """The chain of the configured model, then its renders when ``btf.render.enabled``."""
    from pipeline.btf import runner

    metrics = runner.run(ctx)
    if ctx.cfg.btf.render.enabled:
        from pipeline.btf.render import stage as render_stage

        metrics.update(render_stage.run(ctx))
    return metrics


def figures(cfg: DictConfig, cache_keys: dict[str, str], out: Path) -> list[Path]:
    """Fig. 7 of the finished job, at the pairs of ``conf/tables.yaml``."""
    from pipeline.btf.report import job_figures
    from pipeline.core.report import tables_settings

    pairs = OmegaConf.to_container(tables_settings().fig7.pairs)
    return job_figures(cfg, cache_keys, pairs, out, left_out=BTF.left_out(cfg))


def prepare(cfg: DictConfig) -> None:
    """Resolve the learning rate (``train.lr`` null: the model's ``model.lr``), so the run
    logs the one it trains at; set libgomp's spin count, which it reads once, when torch
    loads: before any stage runs."""
    from pipeline.btf.fast.tuning import set_omp_spin_count

    model = model_of(cfg)
    if model.trains and cfg.train.get("lr") is None:
        cfg.train.lr = cfg.model.lr
    set_omp_spin_count(cfg.train.get("omp_spin_count"))


def check(cfg: DictConfig) -> None:
    """Method A's settings against their declared constraints (no data read)."""
    from pipeline.btf.runner import check_settings_at_the_door

    check_settings_at_the_door(cfg, model_of(cfg))


def unused(cfg: DictConfig) -> list[str]:
    return model_of(cfg).unused(cfg)


def run_name(cfg: DictConfig) -> str:
    return model_of(cfg).run_name(cfg)


# train.*: TrainSettings's fields and defaults; in the config, train.lr null means the
# model's. model.*: each model's typed config (pipeline.btf.models).
_SCHEMAS = (
    ("schema", "train", schema(TrainSettings, "TrainSchema", lr=None)),
    *schemas(),
    *(("schema/btf", name, settings) for name, settings in GROUPS.items()),
)


BTF = Method(
    name="btf",
    paper="A",
    run=run,
    description=(
        "**Method A: Neural BTF with clustering** (PAPERS.md A), the model in `model.name`: "
        "`neural_btf` (one latent per texel), `clustered` (one latent per k-means cluster) "
        "or `pca` (the linear comparator). `rmse`: eq. 10, over the crop's texels and all "
        "its directions, with values divided by the crop's maximum (so in [0, 1]); where "
        "lights were held out of training, `rmse_train_dirs` over the trained directions "
        "and `rmse_heldout_*` over the held-out ones (against nearest and linear "
        "interpolation). Baseline: `rmse_mean_abrdf` predicts every texel as the "
        "crop's mean ABRDF; `rmse_ratio_to_mean_abrdf` = rmse / that (a tag "
        "`training_failed` marks >= 0.9). `bytes_*`: Table 1's sizes. Artifacts: `config/` "
        "(resolved config, overrides), `hydra/` (the job's log), `metrics.json`, the figures."
    ),
    headline=("rmse", "psnr_db", "rmse_ratio_to_mean_abrdf", "bytes_total"),
    reports=("pipeline.btf.report", "pipeline.btf.render.report"),  # Tables 1-2 ..., Fig. 8
    figures=figures,
    prepare=prepare,
    run_name=run_name,
    unused=unused,
    schemas=_SCHEMAS,
    check=check,
    settings=(
        ("train", TrainSettings),
        *(("model", model.config) for model in MODELS.values()),
        *DECLARED.items(),
    ),
)
