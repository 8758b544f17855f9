r"""Method B: MAP reconstruction of an anisotropic BRDF from incomplete measurements.

Hara, Inoue, Urahama (PAPERS.md, B). The specular part follows Ashikhmin-Premoze-Shirley
(eq. 1) with a microfacet distribution f(theta, phi) = rho_s u(theta) v(phi) made of two
constrained Gaussian mixtures (eq. 6-8); the distribution is fitted by EM to an observed
distribution d(theta, phi), alternating with a recomputation of d (section 3).

Pipeline (:func:`fit_microfacet_em`)
------------------------------------
1. Diffuse/specular separation ("any standard method"): rho_d / pi per channel is a low
   percentile (``diffuse_percentile``, default 5) of the measured reflectance -- the
   minimum-over-directions estimate made robust to noise; specular = max(reflectance -
   rho_d / pi, 0).
2. Observed distribution: every measured pair (k1, k2) puts
   specular * 4 g(k1) g(k2) / (<h.n> F(k.h)) into the (theta_h, phi_h) cell of its half
   vector; d is the per-cell mean, 0 in cells no measurement reaches (the paper's holes).
   <h.n> and g are integrated numerically from the current shape q = u v over the grid.
   Rs: at the first outer iteration the middle of the candidate grid; afterwards the
   candidate whose d (normalised over measured cells) has the smallest KL to the current
   f (normalised over the same cells). Rs is only weakly identified by data that stop
   at 60-75 deg (it moves with the grid size), and it sets the grazing Fresnel rise, so
   it is the largest single source of error in the filled region.
3. EM on the normalised d (below) until the objective stops improving.
4. Repeat 2-3 until q changes by less than ``outer_tol`` (max-norm, relative).
5. rho_s per channel: the paper's rho_s = int d_c (eq. A.1) by default; optionally the
   maximum-likelihood scale on the measured cells, sum_obs d_c / sum_obs q
   (``rho_s_from_observed_cells``), which does not shrink when q puts mass outside them.

Boundaries (an extension, off by default). The paper extends u and v to the whole real
line, so a lobe peaked at theta_h = 0 loses the half of its Gaussians below 0 and its peak
comes out low, and v ignores that phi is periodic. ``theta_mode="fold"`` folds u at 0 and
``phi_mode="wrap"`` wraps v with period 2 pi (:func:`~pipeline.brdf_map.microfacet_model.
mixture_images`). Which image a cell's mass came from is one more latent variable, so the
M-step below keeps its closed form with the sums running over images. On the synthetic
anisotropic Beckmann BRDF, folding roughly halves the error where data are missing.

Derivation of the EM (the appendix, re-derived)
-----------------------------------------------
Cells of the grid have centres x_ij = (theta_i, phi_j) and area A = d_theta d_phi (the
paper integrates in d theta d phi, eq. 14). Normalise d_hat = d / sum(d A) as the paper
does (the text above eq. 18), so rho_s = 1 during EM and w_u is relative to unit mass.
The objective maximised (log posterior, eq. 20, up to constants) is

    J = sum_ij A d_hat_ij log q(x_ij) + w_u sum_m alpha_m log u_m,    alpha_m = 1/M,

i.e. -KL(d_hat || q) + log p(u) + const. E-step (eq. 16): lambda_mn = f_mn / f. Because
f_mn = U_m(theta) V_n(phi) with U_m = u_m N(theta; Gamma + tau m, tau^2) (V likewise),
lambda_mn(i, j) = lambda^u_m(i) lambda^v_n(j), lambda^u_m(i) = U_m(theta_i) / u(theta_i).
The M-step objective (eq. 21) therefore splits into two 1-D problems on the marginals
w_i = sum_j A d_hat_ij and a_j = sum_i A d_hat_ij:

    Q_u = sum_{i,m} w_i lambda^u_im [log u_m - log tau - (theta_i - Gamma - tau m)^2 / (2 tau^2)]
          + w_u sum_m alpha_m log u_m - gamma_u (sum_m u_m - 1).

* Weights: dQ/du_m = 0 with the multiplier gives u_m = (W_m + w_u alpha_m) / (W + w_u),
  W_m = sum_i w_i lambda^u_im, W = sum_m W_m (= rho_s); v_n = A_n / A without prior.
* Gamma and tau jointly: with s = 1/tau, b = Gamma/tau the bracket is
  log s - (s theta - b - m)^2 / 2, jointly concave in (s, b). dQ/db = 0 gives
  b = s theta_bar - m_bar (theta_bar = sum w theta / W, m_bar = sum W_m m / W); putting it
  back, Q(s) = W log s - (s^2 S_tt - 2 s S_tm + S_mm)/2 with
  S_tt = sum_i w_i (theta_i - theta_bar)^2, S_tm = sum_im w_i lambda_im (theta_i - theta_bar)(m - m_bar),
  and dQ/ds = 0 is W tau^2 + S_tm tau - S_tt = 0:

      tau = (sqrt(S_tm^2 + 4 W S_tt) - S_tm) / (2 W),   Gamma = theta_bar - tau m_bar.

  Same for (Lambda, sigma) with n and phi. The appendix's pair Gamma = (1/rho_s) sum
  lambda d (theta - tau m), tau = (sqrt(mu^2 + 4 nu rho_s) - mu) / (2 rho_s) with the
  corrected mu = sum lambda d m (theta - Gamma), nu = sum lambda d (theta - Gamma)^2 (the
  print has n, the other axis's index: d/dtau of (theta - Gamma - tau m)^2 brings down m;
  likewise xi needs n) are the two partial stationarity conditions; applying them one
  after the other is one sweep of coordinate ascent whose fixed point is the joint
  solution above, which we use so that every M-step is an exact maximiser.
* With folded or wrapped axes the data points are the images x_it of each cell centre
  with weights w_i lambda_itm (lambda now over images and components); the formulas
  above hold with theta_i replaced by x_it and sums over (i, t).
* A floor tau >= tau_min (``min_std_cells`` grid cells) stops a Gaussian collapsing on a
  single cell; Q profiled over b is concave in s, so max(tau, tau_min) is the constrained
  maximiser and J still never decreases.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.brdf_map.microfacet_model import (
    HemisphereGrid,
    MicrofacetFit,
    MixtureParams,
    constrained_mixture_log_components,
    g_values,
    mean_cos_normal,
    mixture_images,
    schlick_fresnel,
)
from pipeline.brdf_map.settings import MicrofacetEMSettings
from pipeline.core.errors import DataError
from pipeline.data.brdf import MeasuredBRDF, above_horizon, half_vector_angles

# ----------------------------------------------------------------------------- EM kernels


def _axis_responsibilities(x, weights, offset, std, mode):
    """Images (n, T), responsibilities (n, T, M) and log density (n,) of one axis."""
    images = mixture_images(x, offset, std, weights.size, mode)
    with np.errstate(divide="ignore"):
        log_w = np.log(weights)
    log_comp = constrained_mixture_log_components(images.ravel(), log_w, offset, std)
    log_comp = log_comp.reshape(images.shape + (weights.size,))
    # A plain log-sum-exp: scipy's wrapper costs more than the arithmetic at these sizes.
    peak = log_comp.max(axis=(1, 2))
    peak = np.where(np.isfinite(peak), peak, 0.0)
    shifted = np.exp(log_comp - peak[:, None, None])
    total = shifted.sum(axis=(1, 2))
    with np.errstate(divide="ignore"):
        log_mix = np.log(total) + peak
    resp = shifted / np.where(total > 0, total, 1.0)[:, None, None]
    return images, resp, log_mix


def _axis_m_step(images, mass, resp, prior_strength, min_std):
    """Exact maximiser of the 1-D M-step objective (module docstring).

    The data are the images x_it with weights mass_i * lambda_itm; with one image per
    point (the paper's real line) this is the plain weighted formula.
    """
    n_components = resp.shape[-1]
    m = np.arange(1, n_components + 1, dtype=np.float64)
    x = images.ravel()
    joint = (mass[:, None, None] * resp).reshape(-1, n_components)  # w_i lambda_itm
    per_point = joint.sum(axis=1)
    per_component = joint.sum(axis=0)
    total = per_component.sum()
    alpha = np.full(n_components, 1.0 / n_components)
    weights = (per_component + prior_strength * alpha) / (total + prior_strength)
    x_bar = np.sum(per_point * x) / total
    m_bar = np.sum(per_component * m) / total
    s_xx = np.sum(per_point * (x - x_bar) ** 2)
    s_xm = np.sum(joint * (x - x_bar)[:, None] * (m - m_bar)[None, :])
    root = np.sqrt(s_xm**2 + 4.0 * total * s_xx)
    # Two algebraically equal forms of the positive root; pick the one without cancellation.
    std = 2.0 * s_xx / (root + s_xm) if s_xm > 0 else (root - s_xm) / (2.0 * total)
    std = max(float(std), min_std)
    return weights, float(x_bar - std * m_bar), std


def _log_prior(params: MixtureParams, prior_strength: float) -> float:
    """w_u sum_m alpha_m log u_m with alpha_m = 1/M (0 when w_u = 0, even if some u_m = 0)."""
    return float(prior_strength * np.mean(np.log(params.u))) if prior_strength > 0 else 0.0


def _log_likelihood(mass: np.ndarray, log_density: np.ndarray) -> float:
    # Cells without mass contribute nothing (0 log 0 = 0), even where q underflows.
    keep = mass > 0
    return float(np.sum(mass[keep] * log_density[keep]))


def map_objective(
    d_hat: np.ndarray, grid: HemisphereGrid, params: MixtureParams, prior_strength: float
) -> float:
    """J = sum A d_hat log q + w_u sum alpha_m log u_m (maximised; module docstring), for
    ``d_hat`` (n_theta, n_phi) the observed distribution normalised to unit mass
    (sum(d_hat) * cell_area = 1) and ``prior_strength`` = w_u."""
    return _em_iteration(d_hat, grid, params, prior_strength, (0.0, 0.0))[1]


def em_step(
    d_hat: np.ndarray,
    grid: HemisphereGrid,
    params: MixtureParams,
    prior_strength: float,
    min_std: tuple[float, float] = (0.0, 0.0),
) -> MixtureParams:
    """One EM iteration (E-step eq. 16, closed-form M-step) from ``params``: parameters that
    do not decrease :func:`map_objective` (same arguments), with tau and sigma at least
    ``min_std``."""
    return _em_iteration(d_hat, grid, params, prior_strength, min_std)[0]


def _em_iteration(d_hat, grid, params, prior_strength, min_std):
    """New parameters and the objective J of the *input* parameters (from the same E-step)."""
    w, a = d_hat.sum(axis=1) * grid.cell_area, d_hat.sum(axis=0) * grid.cell_area
    images_u, resp_u, log_u = _axis_responsibilities(
        grid.theta, params.u, params.gamma, params.tau, params.theta_mode
    )
    images_v, resp_v, log_v = _axis_responsibilities(
        grid.phi, params.v, params.lam, params.sigma, params.phi_mode
    )
    objective = (
        _log_likelihood(w, log_u) + _log_likelihood(a, log_v) + _log_prior(params, prior_strength)
    )
    u, gamma, tau = _axis_m_step(images_u, w, resp_u, prior_strength, min_std[0])
    v, lam, sigma = _axis_m_step(images_v, a, resp_v, 0.0, min_std[1])
    new = replace(params, u=u, v=v, tau=tau, sigma=sigma, gamma=gamma, lam=lam)
    return new, objective


def initial_params(
    grid: HemisphereGrid,
    n_theta_components: int,
    n_phi_components: int,
    theta_mode: str = "line",
    phi_mode: str = "line",
) -> MixtureParams:
    """Theta_0: uniform weights, Gaussians evenly covering [0, pi/2] and [0, 2 pi]."""
    tau = 0.5 * np.pi / n_theta_components
    sigma = 2.0 * np.pi / n_phi_components
    return MixtureParams(
        u=np.full(n_theta_components, 1.0 / n_theta_components),
        v=np.full(n_phi_components, 1.0 / n_phi_components),
        tau=tau,
        sigma=sigma,
        gamma=-0.5 * tau,
        lam=-0.5 * sigma,
        theta_mode=theta_mode,
        phi_mode=phi_mode,
    )


# ----------------------------------------------------------------------------- the fit


def separate_diffuse(reflectance: np.ndarray, percentile: float) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse albedo rho_d (3,) and specular residual max(reflectance - rho_d / pi, 0)
    (n, 3) of measured ``reflectance`` (n, 3); rho_d / pi is the ``percentile`` of each
    channel (0 = the minimum)."""
    rho_d = np.pi * np.percentile(reflectance, percentile, axis=0)
    return rho_d, np.maximum(reflectance - rho_d[None, :] / np.pi, 0.0)


def _observed_distribution(specular, ratio, cos_kh, cells, rs, grid, counts):
    """Per-cell mean of specular * 4 g1 g2 / (<h.n> F), shape (n_theta, n_phi, 3)."""
    values = specular * (ratio / schlick_fresnel(cos_kh, rs))[:, None]
    n_cells = grid.n_theta * grid.n_phi
    sums = np.stack([np.bincount(cells, values[:, c], minlength=n_cells) for c in range(3)], -1)
    d = sums / np.maximum(counts, 1)[:, None]
    return d.reshape(grid.n_theta, grid.n_phi, 3)


def _kl_on_cells(d: np.ndarray, q: np.ndarray, cells: np.ndarray) -> float:
    """KL between d and q, both normalised over the given cells."""
    d, q = d[cells], q[cells]
    d = d / d.sum()
    q = np.maximum(q / q.sum(), 1e-300)
    pos = d > 0
    return float(np.sum(d[pos] * np.log(d[pos] / q[pos])))


def fit_microfacet_em(
    brdf: MeasuredBRDF, settings: MicrofacetEMSettings | None = None
) -> MicrofacetFit:
    """Fit method B (module docstring) to the ``measured`` samples of ``brdf`` above the
    horizon; the :class:`MicrofacetFit` is evaluable at any pair of directions."""
    settings = MicrofacetEMSettings() if settings is None else settings  # checked when built
    use = brdf.measured & above_horizon(brdf.light, brdf.view)
    if use.sum() < 10:
        raise DataError(
            f"{brdf.source}: {int(use.sum())} measured samples above the horizon, need >= 10"
        )
    if not np.all(np.isfinite(brdf.reflectance[use])):
        raise DataError(f"{brdf.source}: measured reflectance holds non-finite values")
    return _fit(brdf.reflectance[use], brdf.light[use], brdf.view[use], settings, brdf.source)


def _run_em(d_hat, grid, params, s: MicrofacetEMSettings, min_std):
    """EM on a fixed d_hat until J improves by less than tol; returns params and J history."""
    history = []
    # Each iteration's E-step also yields J of the parameters it starts from, so J after
    # iteration t is read at iteration t + 1 (one extra E-step at the end).
    params, previous = _em_iteration(d_hat, grid, params, s.prior_strength, min_std)
    for iteration in range(s.max_em_iter):
        candidate, current = _em_iteration(d_hat, grid, params, s.prior_strength, min_std)
        history.append(current)
        if iteration == s.max_em_iter - 1 or current - previous <= s.tol * max(1.0, abs(previous)):
            break
        params, previous = candidate, current
    return params, history


def _fit(reflectance, light, view, s: MicrofacetEMSettings, source: str) -> MicrofacetFit:
    grid = HemisphereGrid(s.n_theta_cells, s.n_phi_cells)
    rho_d, specular = separate_diffuse(reflectance, s.diffuse_percentile)
    theta_h, phi_h, cos_kh = half_vector_angles(light, view)
    cells = grid.cell_index(theta_h, phi_h)
    counts = np.bincount(cells, minlength=grid.n_theta * grid.n_phi)
    cell_measured = (counts > 0).reshape(grid.n_theta, grid.n_phi)
    min_std = (s.min_std_cells * grid.d_theta, s.min_std_cells * grid.d_phi)
    candidates = np.linspace(s.rs_range[0], s.rs_range[1], s.n_rs)

    params = initial_params(
        grid, s.n_theta_components, s.n_phi_components, s.theta_mode, s.phi_mode
    )
    objective, objective_outer, rs_history = [], [], []
    q_old = params.shape_on_grid(grid)
    for outer in range(s.max_outer_iter):
        ratio = 4.0 * g_values(light, q_old, grid) * g_values(view, q_old, grid)
        ratio /= mean_cos_normal(q_old, grid)

        def observed(rs_value, ratio=ratio):
            return _observed_distribution(specular, ratio, cos_kh, cells, rs_value, grid, counts)

        if outer == 0:
            # The initial q is a broad guess; "closest to it" would mean nothing yet.
            rs = float(candidates[len(candidates) // 2])
        else:
            scores = [_kl_on_cells(observed(c).sum(-1), q_old, cell_measured) for c in candidates]
            rs = float(candidates[int(np.argmin(scores))])
        rs_history.append(rs)
        d = observed(rs)
        mass = d.sum() * grid.cell_area
        if not mass > 0:
            raise DataError(f"{source}: the specular residual is zero everywhere, nothing to fit")
        params, history = _run_em(d.sum(-1) / mass, grid, params, s, min_std)
        objective += history
        objective_outer += [outer] * len(history)
        q_new = params.shape_on_grid(grid)
        change = np.max(np.abs(q_new - q_old)) / max(np.max(np.abs(q_old)), 1e-300)
        q_old = q_new
        if outer > 0 and change < s.outer_tol:
            break

    if s.rho_s_from_observed_cells:
        rho_s = d[cell_measured].sum(axis=0) / q_old[cell_measured].sum()
    else:
        rho_s = d.reshape(-1, 3).sum(axis=0) * grid.cell_area
    return MicrofacetFit(
        params=params,
        rho_s=rho_s,
        rho_d=rho_d,
        rs=rs,
        grid=grid,
        observed=d,
        cell_measured=cell_measured,
        objective=np.array(objective),
        objective_outer=np.array(objective_outer, dtype=int),
        rs_history=rs_history,
    )


def fit_without_prior(
    brdf: MeasuredBRDF, settings: MicrofacetEMSettings | None = None
) -> MicrofacetFit:
    """Baseline: the same fit with w_u = 0 (maximum likelihood, no Dirichlet prior)."""
    settings = MicrofacetEMSettings() if settings is None else settings
    return fit_microfacet_em(brdf, replace(settings, prior_strength=0.0))


def rmse(estimate: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root-mean-square error of ``estimate`` against ``reference``, (n, 3) each, over rows
    and channels; only the rows where ``mask`` (n,) bool is True when it is given."""
    estimate = np.asarray(estimate, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if estimate.shape != reference.shape:
        raise DataError(f"estimate shape {estimate.shape} differs from reference {reference.shape}")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != estimate.shape[:1]:
            raise DataError(f"mask shape {mask.shape} does not match {estimate.shape[:1]} rows")
        estimate, reference = estimate[mask], reference[mask]
    if estimate.size == 0:
        raise DataError("rmse over an empty selection")
    return float(np.sqrt(np.mean((estimate - reference) ** 2)))
