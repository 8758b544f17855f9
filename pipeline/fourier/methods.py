"""Method C's two jobs as the job and the tables command see them
(:class:`pipeline.core.methods.Method`): the per-pixel Fourier fit and the optical pattern.
Light on purpose: the chain is imported when the job runs."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from pipeline.core.methods import Method
from pipeline.core.settings import schema
from pipeline.fourier.settings import FourierSettings, check

if TYPE_CHECKING:
    from pipeline.core.stage import Context


def run_fit(ctx: Context) -> dict[str, float]:
    from pipeline.fourier import runner

    return runner.run(ctx)


def run_pattern(ctx: Context) -> dict[str, float]:
    from pipeline.fourier import pattern_runner

    return pattern_runner.run(ctx)


def _open_maps(*names: str) -> list[tuple[str, type, dataclasses.Field]]:
    return [(name, dict[str, Any], dataclasses.field(default_factory=dict)) for name in names]


# method.*: the fit's settings (defaults in FourierSettings) and the maps the YAML fills.
# The pattern's config extends the fit's: conf/method/fourier_pattern.yaml merges its schema
# after fourier.yaml, which OmegaConf allows for a subclass only.
FOURIER_SCHEMA = schema(
    FourierSettings, "FourierSchema", name="fourier", spec="", segmentation={}, figures={}
)
FOURIER_PATTERN_SCHEMA = dataclasses.make_dataclass(
    "FourierPatternSchema", _open_maps("quilting", "pattern"), bases=(FOURIER_SCHEMA,)
)

FOURIER = Method(
    name="fourier",
    paper="C",
    run=run_fit,
    description=(
        "**Method C: Fourier-series reflectance from a light stack** (PAPERS.md C). "
        "`rmse_validation_*` chose M and lambda; `rmse_test_*` is the report, on held-out "
        "lights never used for a choice; `fourier` against the PTM and HSH baselines."
    ),
    headline=("rmse_test_fourier", "rmse_test_ptm", "rmse_test_hsh"),
    reports=("pipeline.fourier.report",),
    schemas=(("schema", "fourier", FOURIER_SCHEMA),),
    check=check,
    settings=(("method", FourierSettings),),
)
FOURIER_PATTERN = Method(
    name="fourier_pattern",
    paper="C",
    run=run_pattern,
    description=(
        "**Method C: optical pattern.** Regions segmented from the fitted coefficients, "
        "quilted and blended over a target shape; artifacts `pattern/` and `figures/`."
    ),
    headline=("seam_cost_quilting", "seam_cost_random"),
    reports=("pipeline.fourier.report",),
    schemas=(("schema", "fourier_pattern", FOURIER_PATTERN_SCHEMA),),
    check=check,
    settings=(("method", FourierSettings),),
)
