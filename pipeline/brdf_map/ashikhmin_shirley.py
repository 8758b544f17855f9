"""The plain parametric baseline of method B: an Ashikhmin-Shirley fit by least squares."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from pipeline.brdf_map.microfacet_model import ashikhmin_shirley_brdf
from pipeline.core.errors import ConfigError, DataError
from pipeline.data.brdf import MeasuredBRDF, above_horizon


@dataclass(frozen=True)
class AshikhminShirleyFit:
    """Ashikhmin-Shirley anisotropic Phong fit: rd (3,), rs (3,), nu, nv, phi0."""

    rd: np.ndarray
    rs: np.ndarray
    nu: float
    nv: float
    phi0: float
    cost: float

    n_parameters: int = 9

    def parameters(self) -> dict[str, np.ndarray | float]:
        """Fitted values by name (for logging)."""
        return {
            "rd": self.rd.copy(),
            "rs": self.rs.copy(),
            "nu": self.nu,
            "nv": self.nv,
            "phi0": self.phi0,
        }

    def evaluate(self, light: np.ndarray, view: np.ndarray) -> np.ndarray:
        """BRDF of shape (n, 3) at pairs of shape (n, 2)."""
        return ashikhmin_shirley_brdf(light, view, self.rd, self.rs, self.nu, self.nv, self.phi0)


def fit_ashikhmin_shirley(
    brdf: MeasuredBRDF,
    rng: np.random.Generator | None = None,
    max_samples: int | None = None,
    exponent_starts: tuple[tuple[float, float], ...] = ((20.0, 20.0), (100.0, 10.0), (10.0, 100.0)),
) -> AshikhminShirleyFit:
    """Least-squares fit of the Ashikhmin-Shirley BRDF to the measured samples.

    Parameters
    ----------
    rng : numpy.random.Generator, optional
        Draws the subsample when ``max_samples`` is smaller than the measured count.
    max_samples : int, optional
        Fit on at most this many measured samples (speed).
    exponent_starts : tuple of (nu, nv)
        Starting exponents; the best of the local fits is kept.
    """
    use = np.flatnonzero(brdf.measured & above_horizon(brdf.light, brdf.view))
    if use.size < 10:
        raise DataError(f"{brdf.source}: {use.size} measured samples above the horizon, need >= 10")
    if max_samples is not None and use.size > max_samples:
        if max_samples < 10:
            raise ConfigError(f"max_samples={max_samples} must be >= 10")
        if rng is None:
            raise ConfigError("max_samples needs an rng to draw the subsample")
        use = np.sort(rng.choice(use, size=max_samples, replace=False))
    light, view, target = brdf.light[use], brdf.view[use], brdf.reflectance[use]
    rd0 = np.pi * np.percentile(target, 5.0, axis=0)

    def residual(x):
        pred = ashikhmin_shirley_brdf(light, view, x[0:3], x[3:6], np.exp(x[6]), np.exp(x[7]), x[8])
        return (pred - target).ravel()

    lower = [0, 0, 0, 0, 0, 0, np.log(0.1), np.log(0.1), -np.pi]
    upper = [np.inf, np.inf, np.inf, 1, 1, 1, np.log(1e5), np.log(1e5), np.pi]
    best = None
    for nu0, nv0 in exponent_starts:
        x0 = np.concatenate([rd0, [0.05] * 3, [np.log(nu0), np.log(nv0), 0.0]])
        result = least_squares(residual, x0, bounds=(lower, upper), x_scale="jac")
        if best is None or result.cost < best.cost:
            best = result
    x = best.x
    return AshikhminShirleyFit(
        rd=x[0:3].copy(),
        rs=x[3:6].copy(),
        nu=float(np.exp(x[6])),
        nv=float(np.exp(x[7])),
        # The lobe depends on phi - phi0 through cos^2 and sin^2 only: phi0 and phi0 + pi
        # are one fit, reported in [-pi/2, pi/2) so that equal fits log equal values.
        phi0=float(np.mod(x[8] + 0.5 * np.pi, np.pi) - 0.5 * np.pi),
        cost=float(best.cost),
    )
