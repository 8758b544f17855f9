"""Method C's settings (``method.*`` of ``method=fourier`` and ``method=fourier_pattern``),
apart from the numerics so that composing a config (which registers them as Hydra
structured configs) imports none.

The fit's settings are typed fields of :class:`FourierSettings`, the one source of their
defaults: Hydra refuses a misspelt key or a value of the wrong type (``method.lam=big``) as
the config composes, and the settings check their ranges when built (``method.M=-1``). The
nested maps (``segmentation``, ``figures``) keep their defaults in ``conf/method/fourier.yaml``
and their allowed values in :data:`CONSTRAINTS`; :func:`check` reads both before any stage
runs.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from pipeline.core.settings import Integer, OneOf, Real, check_fields, check_settings, setting

SOLVERS = ("auto", "normal", "svd")  # pipeline.fourier.series.SOLVER_NAMES
COLOUR_SPACES = ("rgb", "chromaticity")  # what pipeline.fourier.segmentation segments in
FEATURES = ("mean_colour", "coefficients")  # what k-means clusters


@dataclass(frozen=True)
class FourierSettings:
    """The fit of eq. 19 (:func:`~pipeline.fourier.series.fit_fourier`): ``method.M``,
    ``method.lam``, ``method.clamp_diffuse``, ``method.solver``. Checks itself when built,
    naming a bad value as the job's config does (``method.M=-1 must be an integer >= 0``).

    Attributes
    ----------
    M : int
        Highest harmonic of eq. 16 (the paper picks 10). M = 0 is a valid, degenerate
        model: a_d cos θd + a_0 / √2, the diffuse term plus a constant, with no term in θs
        (no highlight) and nothing for λ to penalise; it is the first point of Fig. 6's
        error-against-M curve. Needs N >= 2M + 2 training images (checked once the data
        is read).
    lam : float
        λ >= 0 of eq. 19 (the paper picks 3.14); 0 = plain least squares (eq. 17).
    clamp_diffuse : bool
        False: the paper's a_d cos θd; True: max(cos θd, 0) (not in the paper).
    solver : {"auto", "normal", "svd"}
        auto: svd at λ = 0, normal at λ > 0 | normal (batched normal equations, fast; at
        λ = 0 a truncated pseudo-inverse) | svd (= ``np.linalg.lstsq``, slower:
        docs/performance.md). See :func:`~pipeline.fourier.series.resolve_solver`.
    """

    M: int = setting(10, Integer(0))
    lam: float = setting(3.14, Real(0.0))
    clamp_diffuse: bool = setting(False, OneOf(True, False))
    solver: str = setting("auto", OneOf(*SOLVERS))

    def __post_init__(self) -> None:
        check_fields(self, "method")


# The nested maps of method.*, whose defaults are in conf/method/fourier.yaml (the
# pattern's quilting.* and pattern.* are checked by pipeline.fourier.pattern_runner).
CONSTRAINTS = {
    "method.segmentation.n_regions": Integer(1),
    "method.segmentation.colour_space": OneOf(*COLOUR_SPACES),
    "method.segmentation.features": OneOf(*FEATURES),
    "method.segmentation.seed": Integer(0, 2**32 - 1),  # k-means' random_state takes 32 bits
    "method.segmentation.n_init": Integer(1),
    "method.figures.n_lights": Integer(1),
    "method.figures.exposure": Real(0.0, closed=False),
}


def fourier_settings(cfg) -> FourierSettings:
    """``method.*`` of the composed config ``cfg`` as :class:`FourierSettings`, which checks
    the values; the structured config has already refused unknown keys and wrong types."""
    from omegaconf import OmegaConf

    method = OmegaConf.to_container(cfg.method, resolve=True)
    return FourierSettings(**{f.name: method[f.name] for f in fields(FourierSettings)})


def check(cfg) -> None:
    """Method C's settings against their declared constraints (no data read)."""
    fourier_settings(cfg)
    check_settings(cfg, CONSTRAINTS)
