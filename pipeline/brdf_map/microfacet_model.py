"""Building blocks of method B's reflectance model (PAPERS.md, B; paper eq. 1-11).

* the constrained Gaussian mixtures u(theta_h) and v(phi_h) (eq. 7-8, normaliser
  1/(sqrt(2 pi) tau) per axis, i.e. eq. 10's 1/(2 pi tau sigma) in 2-D);
* the hemisphere grid on which the observed distribution lives and on which <h.n> (eq. 2)
  and g(k) (eq. 4) are integrated numerically (midpoint rule in (theta, phi) with the
  sin(theta) Jacobian, microfacet normals restricted to the upper hemisphere);
* Schlick's Fresnel term (eq. 3), the microfacet specular BRDF (eq. 1) and
  :class:`MicrofacetFit`, the fitted reconstruction evaluable at any direction pair;
* the Ashikhmin-Shirley (2000) anisotropic Phong BRDF used as a parametric baseline.

Gauge: the BRDF of eq. 1 is unchanged when p is multiplied by a constant (p, <h.n> and
each g scale alike). We therefore compute <h.n> and g from the *shape* q = u v (unit mass
over the (theta, phi) domain of its mixtures) and carry the specular magnitude in rho_s
alone, so that rho(k1, k2) = rho_s q(h) <h.n>_q F(k.h) / (4 g_q(k1) g_q(k2)).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from pipeline.data.brdf import above_horizon, half_vector_angles, to_unit_vectors
from pipeline.data.brdf_models import ashikhmin_shirley_lobe, ashikhmin_shirley_normalization

LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


@dataclass(frozen=True)
class HemisphereGrid:
    """Regular (theta_h, phi_h) grid over the upper hemisphere, cell centres as nodes.

    Attributes
    ----------
    n_theta, n_phi : int
        Cells along theta in [0, pi/2] and phi in [0, 2 pi).
    """

    n_theta: int
    n_phi: int

    @property
    def d_theta(self) -> float:
        return 0.5 * np.pi / self.n_theta

    @property
    def d_phi(self) -> float:
        return 2.0 * np.pi / self.n_phi

    @property
    def theta(self) -> np.ndarray:
        """Cell-centre polar angles, shape (n_theta,)."""
        return (np.arange(self.n_theta) + 0.5) * self.d_theta

    @property
    def phi(self) -> np.ndarray:
        """Cell-centre azimuths, shape (n_phi,)."""
        return (np.arange(self.n_phi) + 0.5) * self.d_phi

    @property
    def cell_area(self) -> float:
        """d_theta * d_phi: the measure of the paper's KL integral (eq. 14), no Jacobian."""
        return self.d_theta * self.d_phi

    def unit_vectors(self) -> np.ndarray:
        """Cell-centre unit vectors, shape (n_theta * n_phi, 3), theta-major."""
        t, p = np.meshgrid(self.theta, self.phi, indexing="ij")
        return to_unit_vectors(np.stack([t.ravel(), p.ravel()], axis=-1))

    def solid_angles(self) -> np.ndarray:
        """Solid angle of each cell, sin(theta) d_theta d_phi, shape (n_theta * n_phi,)."""
        return np.repeat(np.sin(self.theta) * self.cell_area, self.n_phi)

    def cell_index(self, theta_h: np.ndarray, phi_h: np.ndarray) -> np.ndarray:
        """Flat index of the cell holding each (theta_h, phi_h), shape (n,)."""
        i = np.clip((np.asarray(theta_h) / self.d_theta).astype(int), 0, self.n_theta - 1)
        j = np.mod((np.asarray(phi_h) / self.d_phi).astype(int), self.n_phi)
        return i * self.n_phi + j


def constrained_mixture_log_components(
    x: np.ndarray, log_weights: np.ndarray, offset: float, std: float
) -> np.ndarray:
    """log(w_m N(x; offset + std * m, std^2)) for m = 1..M, shape (n, M), at ``x`` (n,).

    ``log_weights`` (M,) are the log w_m; ``offset`` and ``std`` are Gamma (or Lambda) and
    tau (or sigma) of eq. 7 (or 8).
    """
    m = np.arange(1, log_weights.shape[0] + 1)
    z = (np.asarray(x, dtype=np.float64)[:, None] - offset - std * m[None, :]) / std
    return log_weights[None, :] - 0.5 * z**2 - np.log(std) - LOG_SQRT_2PI


def mixture_images(
    x: np.ndarray, offset: float, std: float, n_components: int, mode: str
) -> np.ndarray:
    """Points of the real line whose density adds up to the density at x.

    ``mode="line"`` is the paper's extension to the whole real line (one image, x itself).
    ``mode="fold"`` folds the line at 0 (images x and -x): for theta_h the mass a Gaussian
    puts below 0 lands back on [0, inf) instead of being lost (exact for distributions
    symmetric under h_xy -> -h_xy, where (-theta, phi) and (theta, phi + pi) agree).
    ``mode="wrap"`` makes phi_h periodic (images x + 2 pi k, for every k within 7 std of a
    component mean). The image is a latent variable of the EM, so the M-step stays closed.

    Returns an array of shape (n, n_images) for ``x`` of shape (n,); ``offset`` and ``std``
    are Gamma and tau (or Lambda and sigma) of a mixture of ``n_components``.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if mode == "line":
        return x[:, None]
    if mode == "fold":
        return np.stack([x, -x], axis=-1)
    period = 2.0 * np.pi
    low = offset + std - 7.0 * std
    high = offset + n_components * std + 7.0 * std
    ks = np.arange(np.floor(low / period) - 1, np.ceil(high / period) + 1)
    return x[:, None] + period * ks[None, :]


def constrained_mixture(
    x: np.ndarray, weights: np.ndarray, offset: float, std: float, mode: str = "line"
) -> np.ndarray:
    """u(x) of eq. 7: sum_m w_m N(x; offset + std m, std^2) summed over images; shape of x."""
    x = np.asarray(x, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    images = mixture_images(x.ravel(), offset, std, weights.size, mode)
    with np.errstate(divide="ignore"):
        log_w = np.log(weights)
    comps = constrained_mixture_log_components(images.ravel(), log_w, offset, std)
    return np.exp(comps).sum(axis=1).reshape(images.shape).sum(axis=1).reshape(x.shape)


@dataclass(frozen=True)
class MixtureParams:
    """Shape parameters of f = rho_s u(theta_h) v(phi_h) (eq. 6-8).

    Attributes
    ----------
    u : ndarray of shape (M,)
        Weights of the theta mixture (non-negative, sum 1).
    v : ndarray of shape (N,)
        Weights of the phi mixture (non-negative, sum 1).
    tau, sigma : float
        Shared standard deviation and spacing of the theta / phi Gaussians.
    gamma, lam : float
        Gamma and Lambda: the first means are gamma + tau and lam + sigma.
    theta_mode, phi_mode : str
        How each axis treats the real line (:func:`mixture_images`); the paper uses
        "line" for both.
    """

    u: np.ndarray
    v: np.ndarray
    tau: float
    sigma: float
    gamma: float
    lam: float
    theta_mode: str = "line"
    phi_mode: str = "line"

    def u_of(self, theta: np.ndarray) -> np.ndarray:
        return constrained_mixture(theta, self.u, self.gamma, self.tau, self.theta_mode)

    def v_of(self, phi: np.ndarray) -> np.ndarray:
        phi = np.asarray(phi, dtype=np.float64)
        if self.phi_mode == "wrap":
            phi = np.mod(phi, 2.0 * np.pi)
        return constrained_mixture(phi, self.v, self.lam, self.sigma, self.phi_mode)

    def shape(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """q(theta, phi) = u(theta) v(phi), broadcast over equal shapes."""
        return self.u_of(theta) * self.v_of(phi)

    def shape_on_grid(self, grid: HemisphereGrid) -> np.ndarray:
        """q at the grid's cell centres, shape (n_theta, n_phi)."""
        return np.outer(self.u_of(grid.theta), self.v_of(grid.phi))


def mean_cos_normal(q_grid: np.ndarray, grid: HemisphereGrid) -> float:
    """<h.n> = int (h.n) p(h) dw_h (eq. 2) over the upper hemisphere, p given on the grid."""
    return float(
        np.sum(q_grid.ravel() * np.cos(np.repeat(grid.theta, grid.n_phi)) * grid.solid_angles())
    )


def g_integral(directions: np.ndarray, q_grid: np.ndarray, grid: HemisphereGrid) -> np.ndarray:
    """g(k) = int_{h.k > 0} (h.k) p(h) dw_h (eq. 4) by the midpoint rule on the grid.

    ``directions`` (n, 2) are the ``(theta, phi)`` of k, ``q_grid`` (n_theta, n_phi) the
    distribution at the grid's cell centres; returns shape (n,).
    """
    k = to_unit_vectors(np.asarray(directions, dtype=np.float64).reshape(-1, 2))
    h = grid.unit_vectors()
    mass = q_grid.ravel() * grid.solid_angles()
    out = np.empty(k.shape[0])
    # Chunks bound the (chunk x cells) temporary to about 32 MB.
    chunk = max(1, 4_000_000 // h.shape[0])
    for start in range(0, k.shape[0], chunk):
        dots = k[start : start + chunk] @ h.T
        out[start : start + chunk] = np.maximum(dots, 0.0) @ mass
    return out


def unique_directions(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of (n, 2) directions (rounded to 1e-10) and the inverse index (n,)."""
    rounded = np.ascontiguousarray(np.round(np.asarray(directions, dtype=np.float64), 10))
    # Viewing each (theta, phi) row as one complex number sorts far faster than axis=0.
    keys = rounded.view(np.complex128).ravel()
    unique, inverse = np.unique(keys, return_inverse=True)
    return np.stack([unique.real, unique.imag], axis=-1), inverse.ravel()


def g_values(
    directions: np.ndarray, q_grid: np.ndarray, grid: HemisphereGrid, max_direct: int = 20000
) -> np.ndarray:
    """g(k) at many directions: exact on the distinct ones, or a table when they are many.

    Measured data repeat few directions (UTIA: 288), so integrating once per distinct
    direction is exact and cheap; dense queries (renders, MERL) use a bilinear table in
    (theta_k, phi_k) with 1 x 3 degree nodes, accurate because g is smooth in k.

    Arguments as :func:`g_integral`; ``max_direct`` is the largest number of distinct
    directions integrated directly.
    """
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 2)
    wrapped = np.stack([directions[:, 0], np.mod(directions[:, 1], 2 * np.pi)], axis=-1)
    unique, inverse = unique_directions(wrapped)
    if unique.shape[0] <= max_direct:
        return g_integral(unique, q_grid, grid)[inverse]
    theta_nodes = np.linspace(0.0, 0.5 * np.pi, 91)
    phi_nodes = np.linspace(0.0, 2.0 * np.pi, 121)
    t, p = np.meshgrid(theta_nodes, phi_nodes, indexing="ij")
    table = g_integral(np.stack([t.ravel(), p.ravel()], axis=-1), q_grid, grid)
    interp = RegularGridInterpolator((theta_nodes, phi_nodes), table.reshape(t.shape))
    clipped = np.stack([np.clip(wrapped[:, 0], 0.0, 0.5 * np.pi), wrapped[:, 1]], axis=-1)
    return interp(clipped)


def schlick_fresnel(cos_kh: np.ndarray, rs: float) -> np.ndarray:
    """F = Rs + (1 - Rs)(1 - k.h)^5 (eq. 3)."""
    return rs + (1.0 - rs) * (1.0 - np.asarray(cos_kh)) ** 5


def microfacet_specular(
    light: np.ndarray,
    view: np.ndarray,
    params: MixtureParams,
    rho_s: np.ndarray,
    rs: float,
    grid: HemisphereGrid,
) -> np.ndarray:
    """Specular BRDF of eq. 11 with the gauge of this module; 0 below the horizon.

    Parameters
    ----------
    light, view : ndarray of shape (n, 2)
    rho_s : ndarray of shape (3,)
        Per-channel specular magnitude.
    rs : float
        Schlick reflectance at normal incidence.
    grid : HemisphereGrid
        Grid for the <h.n> and g integrals.

    Returns
    -------
    ndarray of shape (n, 3)
    """
    light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
    view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
    above = above_horizon(light, view)
    q_grid = params.shape_on_grid(grid)
    mean_hn = mean_cos_normal(q_grid, grid)
    g_light = g_values(light, q_grid, grid)
    g_view = g_values(view, q_grid, grid)
    theta_h, phi_h, cos_kh = half_vector_angles(light, view)
    q = params.shape(theta_h, phi_h)
    denom = 4.0 * np.maximum(g_light * g_view, 1e-300)
    value = np.where(above, q * mean_hn * schlick_fresnel(cos_kh, rs) / denom, 0.0)
    return value[:, None] * np.asarray(rho_s, dtype=np.float64)[None, :]


@dataclass
class MicrofacetFit:
    """A fitted reconstruction: Theta = {rho_s, u, v, tau, sigma, Gamma, Lambda, rho_d, Rs}.

    Attributes
    ----------
    params : MixtureParams
        u (M,), v (N,), tau, sigma, Gamma (gamma), Lambda (lam).
    rho_s, rho_d : ndarray of shape (3,)
        Specular magnitude and diffuse albedo per channel.
    rs : float
        Schlick Rs chosen from the candidate grid.
    grid : HemisphereGrid
    observed : ndarray of shape (n_theta, n_phi, 3)
        Last observed distribution d per channel (0 in unmeasured cells).
    cell_measured : ndarray of shape (n_theta, n_phi), bool
        Cells reached by at least one measured half vector.
    objective : ndarray of shape (n_iterations,)
        J after every EM iteration, all outer iterations concatenated.
    objective_outer : ndarray of shape (n_iterations,), int
        Outer iteration of each entry of ``objective`` (J is comparable only within one).
    rs_history : list of float
        Rs used at each outer iteration.
    """

    params: MixtureParams
    rho_s: np.ndarray
    rho_d: np.ndarray
    rs: float
    grid: HemisphereGrid
    observed: np.ndarray
    cell_measured: np.ndarray
    objective: np.ndarray
    objective_outer: np.ndarray
    rs_history: list = field(default_factory=list)

    @property
    def n_parameters(self) -> int:
        """Stored numbers in Theta: 3 rho_s + M + N + 4 (tau, sigma, Gamma, Lambda) + 3 rho_d + Rs.

        Two fewer are free (u and v each sum to 1).
        """
        return 3 + self.params.u.size + self.params.v.size + 4 + 3 + 1

    def parameters(self) -> dict[str, np.ndarray | float]:
        """Theta by name (for logging): rho_s, u, v, tau, sigma, Gamma, Lambda, rho_d, Rs."""
        p = self.params
        return {
            "rho_s": self.rho_s.copy(),
            "u": p.u.copy(),
            "v": p.v.copy(),
            "tau": float(p.tau),
            "sigma": float(p.sigma),
            "Gamma": float(p.gamma),
            "Lambda": float(p.lam),
            "rho_d": self.rho_d.copy(),
            "Rs": float(self.rs),
        }

    def distribution(self, theta_h: np.ndarray, phi_h: np.ndarray) -> np.ndarray:
        """f = rho_s q per channel at half-vector angles, shape (..., 3)."""
        q = self.params.shape(np.asarray(theta_h), np.asarray(phi_h))
        return q[..., None] * self.rho_s

    def distribution_grid(self) -> np.ndarray:
        """f at the grid's cell centres, shape (n_theta, n_phi, 3)."""
        return self.params.shape_on_grid(self.grid)[..., None] * self.rho_s

    def evaluate(self, light: np.ndarray, view: np.ndarray) -> np.ndarray:
        """Reconstructed BRDF rho_d / pi + specular (eq. 23 without the cosine), shape (n, 3).

        Parameters
        ----------
        light, view : ndarray of shape (n, 2)
            ``(theta, phi)`` in radians; pairs below the horizon give 0.
        """
        light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
        view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
        spec = microfacet_specular(light, view, self.params, self.rho_s, self.rs, self.grid)
        return spec + above_horizon(light, view)[:, None] * (self.rho_d / np.pi)[None, :]


def ashikhmin_shirley_brdf(
    light: np.ndarray,
    view: np.ndarray,
    rd: np.ndarray,
    rs: np.ndarray,
    nu: float,
    nv: float,
    phi0: float = 0.0,
) -> np.ndarray:
    """Ashikhmin-Shirley (2000) anisotropic Phong BRDF, diffuse and specular.

    rho_s = sqrt((nu+1)(nv+1)) / (8 pi) (n.h)^(nu cos^2 phi + nv sin^2 phi)
            / ((h.k) max(n.k1, n.k2)) F(k.h),
    rho_d = 28 Rd / (23 pi) (1 - Rs) (1 - (1 - n.k1/2)^5) (1 - (1 - n.k2/2)^5),
    phi = phi_h - phi0 (the azimuth of the half vector from the ``nu`` axis).

    Parameters
    ----------
    light, view : ndarray of shape (n, 2)
    rd, rs : ndarray of shape (3,)
        Diffuse and specular (Schlick) reflectances per channel.
    nu, nv : float
        Phong exponents along and across the axis at azimuth ``phi0``.

    Returns
    -------
    ndarray of shape (n, 3); 0 below the horizon.
    """
    light = np.asarray(light, dtype=np.float64).reshape(-1, 2)
    view = np.asarray(view, dtype=np.float64).reshape(-1, 2)
    rd = np.asarray(rd, dtype=np.float64)[None, :]
    rs = np.asarray(rs, dtype=np.float64)[None, :]
    cos1, cos2 = np.cos(light[:, 0]), np.cos(view[:, 0])
    above = (cos1 > 0) & (cos2 > 0)
    theta_h, phi_h, cos_kh = half_vector_angles(light, view)
    # The half vector in the frame whose tangent (the nu axis) lies at azimuth phi0.
    phi, sin_h = phi_h - phi0, np.sin(theta_h)
    lobe = ashikhmin_shirley_normalization(nu, nv) * ashikhmin_shirley_lobe(
        np.cos(theta_h), sin_h * np.cos(phi), sin_h * np.sin(phi), nu, nv
    )
    lobe = lobe / np.maximum(cos_kh * np.maximum(cos1, cos2), 1e-6)
    fresnel = rs + (1.0 - rs) * (1.0 - cos_kh[:, None]) ** 5
    c1 = np.clip(cos1, 0.0, 1.0)[:, None]
    c2 = np.clip(cos2, 0.0, 1.0)[:, None]
    diffuse = 28.0 * rd / (23.0 * np.pi) * (1.0 - rs)
    diffuse = diffuse * (1.0 - (1.0 - c1 / 2.0) ** 5) * (1.0 - (1.0 - c2 / 2.0) ** 5)
    return np.where(above[:, None], diffuse + lobe[:, None] * fresnel, 0.0)
