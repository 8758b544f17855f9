"""Stereographic coordinates of directions (PAPERS.md A, eq. 7-9), numpy only.

Kept apart from the torch model so that code that only needs direction features (the
interpolation baselines, a cached rerun) does not import torch.
"""

from __future__ import annotations

import numpy as np


def stereographic(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Stereographic coordinates, ndarray of shape theta.shape + (2,), of directions on the
    upper hemisphere (eq. 7-9) at ``theta``, ``phi`` (array_like of one shape, radians).

    R = sin(pi - theta) / (1 - cos(pi - theta)) = tan(theta / 2), so theta = 0 maps to the
    origin and theta = 90 degrees to the unit circle.
    """
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    radius = np.tan(theta / 2.0)
    return np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=-1)


def direction_features(directions: np.ndarray) -> np.ndarray:
    """(n, 4) = (theta_l, phi_l, theta_v, phi_v) -> (n, 4) float32 decoder inputs."""
    directions = np.asarray(directions, dtype=np.float64)
    light = stereographic(directions[:, 0], directions[:, 1])
    view = stereographic(directions[:, 2], directions[:, 3])
    return np.concatenate([light, view], axis=1).astype(np.float32)
