"""Method B's settings, apart from the EM code so that composing a config (which registers
them as a Hydra structured config) imports no numerics."""

from __future__ import annotations

from dataclasses import dataclass, fields

from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, ListOf, OneOf, Real, check_fields, setting

RS_RANGE_METAL = (0.5, 0.9)
RS_RANGE_DIELECTRIC = (0.02, 0.2)


@dataclass(frozen=True)
class MicrofacetEMSettings:
    """Settings of :func:`fit_microfacet_em`: ``method.*`` of ``method=brdf_map``.

    Each field declares what it may be; the settings check themselves when built and name
    a bad one as the job's config does (``method.n_theta_cells=0 must be an integer >=
    1``), so a job refuses it before any stage runs (:func:`em_settings`).

    Attributes
    ----------
    n_theta_components : int
        M, Gaussians in u(theta_h).
    n_phi_components : int
        N, Gaussians in v(phi_h).
    prior_strength : float
        w_u, strength of the Dirichlet prior on u (alpha_m = 1/M), relative to the unit
        mass of the normalised d; 0 gives the maximum-likelihood fit. The paper gives no
        value; 0.05 floors each u_m at about 0.4 % (M = 12) without flattening the lobe.
    n_theta_cells, n_phi_cells : int
        Grid of d over theta_h in [0, 90] deg and phi_h in [0, 360) deg; also the
        quadrature grid of <h.n> and g.
    rs_range : (float, float)
        Schlick Rs candidates span this interval: (0.02, 0.2) non-metals, (0.5, 0.9) metals.
    n_rs : int
        Number of equally spaced Rs candidates.
    diffuse_percentile : float
        Percentile of the measured reflectance taken as rho_d / pi (0 = minimum).
    tol : float
        EM stops when the objective improves by less than tol * max(1, |J|).
    max_em_iter : int
        EM iterations per outer iteration, at most.
    outer_tol : float
        Outer loop stops when q changes by less than this (relative max-norm).
    max_outer_iter : int
        Outer iterations (recompute d, then EM) at most.
    min_std_cells : float
        Lower bound on tau and sigma, in grid cells of their axis.
    rho_s_from_observed_cells : bool
        Scale rho_s by maximum likelihood over measured cells (True) or use the paper's
        rho_s = int d (False).
    theta_mode : {"line", "fold"}
        u on the real line as in the paper, or folded at the pole (no mass lost below 0).
    phi_mode : {"line", "wrap"}
        v on the real line as in the paper, or periodic in phi.
    """

    n_theta_components: int = setting(12, Integer(1))
    n_phi_components: int = setting(16, Integer(1))
    prior_strength: float = setting(0.05, Real(0.0))
    n_theta_cells: int = setting(45, Integer(1))
    n_phi_cells: int = setting(96, Integer(1))
    rs_range: tuple[float, float] = setting(RS_RANGE_DIELECTRIC, ListOf(Real(0.0, high=1.0), 2))
    n_rs: int = setting(10, Integer(1))
    diffuse_percentile: float = setting(5.0, Real(0.0, high=100.0))
    tol: float = setting(1e-7, Real(0.0, closed=False))
    max_em_iter: int = setting(300, Integer(1))
    outer_tol: float = setting(1e-3, Real(0.0, closed=False))
    max_outer_iter: int = setting(8, Integer(1))
    min_std_cells: float = setting(0.5, Real(0.0, closed=False))
    rho_s_from_observed_cells: bool = setting(False, OneOf(True, False))
    theta_mode: str = setting("line", OneOf("line", "fold"))
    phi_mode: str = setting("line", OneOf("line", "wrap"))

    def __post_init__(self) -> None:
        check_fields(self, "method")
        low, high = self.rs_range
        if low > high:
            raise ConfigError(f"method.rs_range={self.rs_range!r} must be (low, high), low <= high")


def em_settings(cfg) -> MicrofacetEMSettings:
    """``method.*`` of the composed config ``cfg`` as :class:`MicrofacetEMSettings`, which
    checks the values; the structured config of ``conf/method/brdf_map.yaml`` has already
    refused unknown keys and values of the wrong type."""
    from omegaconf import OmegaConf

    method = OmegaConf.to_container(cfg.method, resolve=True)
    values = {f.name: method[f.name] for f in fields(MicrofacetEMSettings) if f.name in method}
    if isinstance(values.get("rs_range"), list):
        values["rs_range"] = tuple(values["rs_range"])
    return MicrofacetEMSettings(**values)
