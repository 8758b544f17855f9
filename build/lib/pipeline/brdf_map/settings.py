"""Method B's settings, apart from the EM code so that composing a config (which registers
them as a Hydra structured config) imports no numerics."""

from __future__ import annotations

from dataclasses import dataclass

RS_RANGE_METAL = (0.5, 0.9)
RS_RANGE_DIELECTRIC = (0.02, 0.2)


@dataclass(frozen=True)
class MicrofacetEMSettings:
    """Settings of :func:`fit_microfacet_em`.

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

    n_theta_components: int = 12
    n_phi_components: int = 16
    prior_strength: float = 0.05
    n_theta_cells: int = 45
    n_phi_cells: int = 96
    rs_range: tuple[float, float] = RS_RANGE_DIELECTRIC
    n_rs: int = 10
    diffuse_percentile: float = 5.0
    tol: float = 1e-7
    max_em_iter: int = 300
    outer_tol: float = 1e-3
    max_outer_iter: int = 8
    min_std_cells: float = 0.5
    rho_s_from_observed_cells: bool = False
    theta_mode: str = "line"
    phi_mode: str = "line"
