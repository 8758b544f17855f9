"""Method A's three models as the job and the tables command see them
(:class:`pipeline.core.methods.Method`): Neural BTF, its clustered variant and the PCA
comparator. Light on purpose: the functions here import the chain when called."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from pipeline.btf.train_settings import TrainSettings
from pipeline.core.methods import Method
from pipeline.core.settings import schema

if TYPE_CHECKING:
    from pipeline.core.stage import Context

_DESCRIPTION = (
    "**Method A: Neural BTF{what}** (PAPERS.md A). `rmse`: eq. 10, over the crop's texels "
    "and the directions the model was trained on, with values divided by the crop's maximum "
    "(so in [0, 1]); held-out lights apart (`rmse_heldout_*`, against nearest and linear "
    "interpolation). Baseline: `rmse_mean_abrdf` predicts every texel as the crop's mean "
    "ABRDF; `rmse_ratio_to_mean_abrdf` = rmse / that (a tag `training_failed` marks >= 0.9). "
    "`bytes_*`: Table 1's sizes. Artifacts: `config/` (resolved config, overrides), "
    "`hydra/` (the job's log), `metrics.json`, the figures."
)
_REPORTS = ("pipeline.btf.report", "pipeline.btf.render.report")  # Tables 1-2 ..., Fig. 8, Tables 3-4
_HEADLINE = ("rmse", "rmse_ratio_to_mean_abrdf", "bytes_total")


def run(ctx: Context) -> dict[str, float]:
    """The chain of the configured model, then its renders when ``btf.render.enabled``."""
    from pipeline.btf import runner

    cfg = ctx.cfg
    metrics = runner.run_linear(ctx) if cfg.method.name == "pca" else runner.run(ctx)
    if cfg.btf.render.enabled:
        from pipeline.btf.render import stage as render_stage

        metrics.update(render_stage.run(ctx))
    return metrics


def figures(cfg: DictConfig, cache_keys: dict[str, str], out: Path) -> list[Path]:
    """Fig. 7 of the finished job, at the pairs of ``conf/tables.yaml``."""
    from pipeline.btf.report import job_figures
    from pipeline.core.report import tables_settings

    pairs = OmegaConf.to_container(tables_settings().fig7.pairs)
    return job_figures(cfg, cache_keys, pairs, out)


def prepare(cfg: DictConfig) -> None:
    """Resolve the learning rate (``train.lr`` null: the method's ``method.lr``), so the run
    logs the one it trains at; set libgomp's spin count, which it reads once, when torch
    loads: before any stage runs."""
    from pipeline.btf.fast.tuning import set_omp_spin_count

    if cfg.train.get("lr") is None:
        cfg.train.lr = cfg.method.get("lr")

    set_omp_spin_count(cfg.train.get("omp_spin_count"))


def unused(cfg: DictConfig) -> list[str]:
    """``method.lr`` is only the default of ``train.lr``, which :func:`prepare` resolves."""
    return ["method.lr"]


def unused_by_pca(cfg: DictConfig) -> list[str]:
    """PCA trains nothing: neither ``train.*`` nor the learning rate makes its numbers."""
    return ["method.lr", *(f"train.{key}" for key in cfg.train)]


# train.*: TrainSettings's fields and defaults; in the config, train.lr null means the method's.
_SCHEMAS = (("schema", "train", schema(TrainSettings, "TrainSchema", lr=None)),)


def _name_with_k(cfg: DictConfig) -> str:
    return f"{cfg.method.name} k={cfg.method.k} s{cfg.seed}"


NEURAL_BTF = Method(
    name="neural_btf", paper="A", run=run, description=_DESCRIPTION.format(what=""),
    headline=_HEADLINE, reports=_REPORTS, figures=figures, prepare=prepare,
    unused=unused, schemas=_SCHEMAS,
)
CLUSTERED = Method(
    name="clustered", paper="A", run=run,
    description=_DESCRIPTION.format(what=" with clustering: one latent per k-means cluster"),
    headline=_HEADLINE, reports=_REPORTS, figures=figures, prepare=prepare,
    run_name=_name_with_k, unused=unused, schemas=_SCHEMAS,
)
PCA = Method(
    name="pca", paper="A", run=run,
    description=(
        "**Method A's comparator: PCA at matched bytes.** Each texel's ABRDF as a mean plus "
        "principal components (as many as the bytes of `method.match_clustered_k` allow, in "
        "`method.dtype`); `rmse` and `rmse_mean_abrdf` as for the neural models (eq. 10, "
        "values divided by the crop's maximum)."
    ),
    headline=_HEADLINE, reports=_REPORTS, prepare=prepare, unused=unused_by_pca,
    schemas=_SCHEMAS,
)
