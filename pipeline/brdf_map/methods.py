"""Method B as the job and the tables command see it (:class:`pipeline.core.methods.Method`).
Light on purpose: the chain is imported when the job runs."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pipeline.brdf_map.settings import MicrofacetEMSettings, em_settings
from pipeline.core.methods import Method
from pipeline.core.settings import schema

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from pipeline.core.stage import Context


def run(ctx: Context) -> dict[str, float]:
    from pipeline.brdf_map import runner

    return runner.run(ctx)


def check(cfg: DictConfig) -> None:
    """Method B's settings (``method.*``) against their declared constraints (no data read)."""
    em_settings(cfg)


# method.*: the EM's settings (defaults in MicrofacetEMSettings) and what the YAML adds.
_SCHEMA = schema(
    MicrofacetEMSettings, "BrdfMapSchema", name="brdf_map", spec="", baselines={}, figures={}
)

BRDF_MAP = Method(
    name="brdf_map",
    paper="B",
    run=run,
    description=(
        "**Method B: MAP reconstruction of an anisotropic BRDF** (PAPERS.md B). "
        "`rmse_measured*`: at the measured directions; `rmse_missing*`: at the missing ones "
        "against the ground truth (near and off the mirror direction); suffixes `_noprior` "
        "and `_as` are the fit without the prior and the Ashikhmin-Shirley baseline."
    ),
    headline=("rmse_missing", "rmse_missing_noprior", "rmse_missing_as", "rmse_measured"),
    reports=("pipeline.brdf_map.report",),
    schemas=(("schema", "brdf_map", _SCHEMA),),
    check=check,
    settings=(("method", MicrofacetEMSettings),),
)
