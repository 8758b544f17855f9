"""Fourier-series per-pixel BRDF model for a fixed camera (PAPERS.md C, eq. 4, 14-19).

Each pixel p has a two-variable BRDF s = f_p(θd, θs) (eq. 4): θd is the angle between
the light l and the normal n, θs the angle between the mirror direction of the light,
r = 2 (n·l) n - l, and the view v. Eq. 16 in real form::

    f_p(θd, θs) = a_d cos θd + a_0 / √2 + Σ_{m=1..M} (a_m cos mθs + b_m sin mθs)

Coefficients are stored per pixel and channel in this order (K = 2M + 2)::

    [a_d, a_0, a_1, b_1, a_2, b_2, ..., a_M, b_M]

They are fitted by regularized linear least squares (eq. 19)::

    E_r = Σ_n r_n² + λ Σ_{m=1..M} m² (a_m² + b_m²)

λ = 0 is plain least squares (eq. 17), solved by a batched SVD with ``np.linalg.lstsq``'s
cutoff (round-off only); λ > 0 by the normal equations, which the penalty keeps well
conditioned (``solver="auto"``, :func:`resolve_solver`). The unregularized design is
badly conditioned on the paper's 6 x 55 light grid (cond(A) ~ 1e12 at M = 10, see
:func:`design_condition`): the plain fit shows the blow-up at high M that motivates eq. 19.

The penalty is the Parseval form of ∫ |g'(θs)|² (eq. 18) up to the factor π, which the
paper folds into λ; a_d and a_0 are not penalized. Where the normal equals the view
(n = v), θs = θd for every light, so a_d and a_1 are not separately identifiable: with
λ > 0 the penalty settles it (a_1 → 0), with λ = 0 the minimum-norm split is returned.
Renders on the fitting normals are unaffected; renders on other normals are not. Every
pixel has its own design matrix (its normal differs), so the fit solves one small system
per pixel, all at once in batches (stacked numpy linear algebra), never in a Python loop
over pixels.

Example
-------
>>> rng = np.random.default_rng(0)
>>> lights = rng.normal(size=(30, 3)); lights[:, 2] = np.abs(lights[:, 2]) + 0.5
>>> normals = np.tile([0.3, 0.0, 0.95], (2, 2, 1)) / np.hypot(0.3, 0.95)
>>> coeffs = rng.normal(size=(2, 2, 3, 6))  # M = 2
>>> images = render_fourier(coeffs, lights, normals)
>>> np.allclose(fit_fourier(images, lights, normals, M=2, lam=0.0), coeffs, atol=1e-4)
True
"""

from __future__ import annotations

import numpy as np

from pipeline.core.errors import ConfigError

VIEW = (0.0, 0.0, 1.0)
# Pixels per batch of normal equations: bounds the (pixels, lights, K) design tensor to
# about 64 MB in float64 so that a 400x400 capture fits on a small machine.
_BATCH_BYTES = 64 * 2**20
# Relative eigenvalue cutoff of the normal equations. Forming AᵀA loses everything below
# about eps·‖AᵀA‖, so eigenvalues under 1e-14 of the largest are round-off: dropping
# them keeps systems with cond(A) up to ~1e7 exact and truncates the rest (a truncated
# pseudo-inverse). With λ > 0 the penalty lifts the small eigenvalues, so nothing is
# dropped; without regularization the paper's geometry is far worse: on the 6 x 55
# light grid, cond(A) is ~1e12 at M = 10 for a generic normal (θs spans well under a
# period, so high harmonics are nearly dependent) -- the reason eq. 19 is needed, and the
# reason λ = 0 is not solved this way (see ``resolve_solver``).
_EIG_CUTOFF = 1e-14


def fourier_penalty(M: int) -> np.ndarray:
    """Diagonal of the eq. 19 penalty, shape (2M + 2,): [0, 0, 1, 1, 4, 4, ..., M², M²]."""
    orders = np.repeat(np.arange(1, M + 1, dtype=np.float64), 2)
    return np.concatenate([[0.0, 0.0], orders**2])


def check_dirs(light_dirs, name: str = "light_dirs") -> tuple[np.ndarray, bool]:
    """Light directions as unit float64 (n, 3); also whether a single (3,) was given."""
    dirs = np.asarray(light_dirs, dtype=np.float64)
    single = dirs.ndim == 1
    dirs = np.atleast_2d(dirs)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise ConfigError(f"{name} must have shape (3,) or (n, 3), got {np.shape(light_dirs)}")
    norm = np.linalg.norm(dirs, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-9):
        bad = int(np.flatnonzero(~(np.isfinite(norm) & (norm >= 1e-9)))[0])
        raise ConfigError(f"{name}[{bad}] = {dirs[bad].tolist()} is not a direction")
    return dirs / norm[:, None], single


def _check_view(view) -> np.ndarray:
    view_dirs, _ = check_dirs(view, "view")
    if len(view_dirs) != 1:
        raise ConfigError(f"view must be one direction of shape (3,), got {np.shape(view)}")
    return view_dirs[0]


def _check_normals(normals, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Unit normals (H, W, 3), float64; a single (3,) normal is broadcast to ``shape``."""
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape == (3,):
        if shape is None:
            raise ConfigError("a single normal of shape (3,) needs the image size")
        normals = np.broadcast_to(normals, (*shape, 3))
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ConfigError(f"normals must have shape (H, W, 3) or (3,), got {normals.shape}")
    if shape is not None and normals.shape[:2] != tuple(shape):
        raise ConfigError(f"normals are {normals.shape[:2]} but the images are {tuple(shape)}")
    norm = np.linalg.norm(normals, axis=-1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-9):
        raise ConfigError("normals contain zero or non-finite vectors")
    return normals / norm[..., None]


def check_images(images, n_lights: int) -> np.ndarray:
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[3] != 3:
        raise ConfigError(f"images must have shape (n, H, W, 3), got {images.shape}")
    if images.shape[0] != n_lights:
        raise ConfigError(f"{images.shape[0]} images but {n_lights} light directions")
    return images


def check_coeffs(coeffs, n_coeffs: int | None = None) -> np.ndarray:
    coeffs = np.asarray(coeffs)
    if coeffs.ndim != 4 or coeffs.shape[2] != 3:
        raise ConfigError(f"coeffs must have shape (H, W, 3, K), got {coeffs.shape}")
    if n_coeffs is not None and coeffs.shape[3] != n_coeffs:
        raise ConfigError(f"coeffs have K={coeffs.shape[3]} terms, expected {n_coeffs}")
    return coeffs


def _features(
    light_dirs: np.ndarray, normals: np.ndarray, view: np.ndarray, M: int, clamp_diffuse: bool
) -> np.ndarray:
    """Design tensor, shape (P, n, 2M + 2), for P unit normals (P, 3) and n lights."""
    cos_d = normals @ light_dirs.T  # (P, n): cos θd
    # r·v with r = 2 (n·l) n - l, without forming r: 2 (n·l)(n·v) - l·v.
    cos_s = 2.0 * cos_d * (normals @ view)[:, None] - (light_dirs @ view)[None, :]
    theta_s = np.arccos(np.clip(cos_s, -1.0, 1.0))
    features = np.empty((*cos_d.shape, 2 * M + 2), dtype=np.float64)
    features[..., 0] = np.maximum(cos_d, 0.0) if clamp_diffuse else cos_d
    features[..., 1] = 1.0 / np.sqrt(2.0)
    orders = np.arange(1, M + 1, dtype=np.float64)
    angles = theta_s[..., None] * orders  # (P, n, M)
    features[..., 2::2] = np.cos(angles)
    features[..., 3::2] = np.sin(angles)
    return features


def _pixel_batches(n_pixels: int, n_lights: int, n_coeffs: int):
    """Slices of at most ``_BATCH_BYTES`` of design tensor each, covering ``n_pixels``."""
    step = max(1, _BATCH_BYTES // (8 * max(1, n_lights) * n_coeffs))
    for start in range(0, n_pixels, step):
        yield slice(start, min(start + step, n_pixels))


def _solve_normal(design: np.ndarray, observed: np.ndarray, penalty: np.ndarray) -> np.ndarray:
    """Eq. 19 by batched normal equations: (AᵀA + λD) x = Aᵀy per pixel.

    design (P, n, K), observed (P, n, C), penalty (K,) -> (P, K, C). A symmetric
    eigendecomposition with a relative cutoff rather than a plain ``solve``: with λ = 0
    some pixels are exactly rank-deficient (where the normal equals the view,
    cos θs = cos θd for every light, so two columns coincide), and a plain solve blows
    round-off up into huge coefficients. Dropping eigenvalues below ``_EIG_CUTOFF``
    times the largest gives the minimum-norm least-squares solution there.
    """
    design_t = design.transpose(0, 2, 1)  # (P, K, n)
    gram = design_t @ design  # (P, K, K)
    diagonal = np.arange(gram.shape[1])
    gram[:, diagonal, diagonal] += penalty
    eigvals, eigvecs = np.linalg.eigh(gram)
    keep = eigvals > _EIG_CUTOFF * eigvals[:, -1:]
    inverse = np.where(keep, 1.0 / np.where(keep, eigvals, 1.0), 0.0)
    projected = eigvecs.transpose(0, 2, 1) @ (design_t @ observed)  # (P, K, C)
    return eigvecs @ (inverse[..., None] * projected)


def _solve_svd(design: np.ndarray, observed: np.ndarray, penalty: np.ndarray) -> np.ndarray:
    """Eq. 19 by batched SVD of the augmented system [A; sqrt(λD)] x = [y; 0].

    Works on cond(A) instead of cond(A)², like ``np.linalg.lstsq`` and with its cutoff.
    With λ = 0 the zero rows are left out, so the result is ``lstsq(A, y)`` itself.
    Slower (docs/performance.md).
    """
    n_pixels, n_rows, n_coeffs = design.shape
    if np.any(penalty):
        root = np.broadcast_to(np.diag(np.sqrt(penalty)), (n_pixels, n_coeffs, n_coeffs))
        design = np.concatenate([design, root], axis=1)
        zeros = np.zeros((n_pixels, n_coeffs, observed.shape[2]))
        observed = np.concatenate([observed, zeros], axis=1)
    left, singular, right_t = np.linalg.svd(design, full_matrices=False)
    keep = singular > _lstsq_cutoff(*design.shape[1:]) * singular[:, :1]
    inverse = np.where(keep, 1.0 / np.where(keep, singular, 1.0), 0.0)
    projected = left.transpose(0, 2, 1) @ observed  # (P, K, C)
    return right_t.transpose(0, 2, 1) @ (inverse[..., None] * projected)


def _lstsq_cutoff(n_rows: int, n_coeffs: int) -> float:
    """``np.linalg.lstsq``'s default relative cutoff of the singular values (rcond=None)."""
    return float(np.finfo(np.float64).eps * max(n_rows, n_coeffs))


_SOLVERS = {"normal": _solve_normal, "svd": _solve_svd}
SOLVER_NAMES = ("auto", *_SOLVERS)


def resolve_solver(solver: str, lam: float) -> str:
    """The solver that actually runs: ``"auto"`` is ``"svd"`` at λ = 0, ``"normal"`` above.

    Only an SVD solves the badly conditioned λ = 0 problem without truncating; with λ > 0
    the normal equations are several times faster and agree with it. ``"normal"`` and
    ``"svd"`` are used as given (``"normal"`` at λ = 0 is kept to compare).
    """
    if solver not in SOLVER_NAMES:
        raise ConfigError(f"solver must be one of {list(SOLVER_NAMES)}, got {solver!r}")
    if solver == "auto":
        return "svd" if lam == 0 else "normal"
    return solver


def _one_blas_thread():
    # threadpoolctl ships with scikit-learn. The batched LAPACK calls are thousands of
    # tiny problems: BLAS threads only add overhead, and on a busy machine OpenBLAS's
    # threaded SVD of such stacks was far slower than single-threaded (docs/performance.md).
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def _fit_kernel(images, light_dirs, normals, view, M, lam, clamp_diffuse, solver) -> np.ndarray:
    n_lights, height, width, _ = images.shape
    n_coeffs = 2 * M + 2
    n_pixels = height * width
    targets = images.reshape(n_lights, n_pixels, 3)
    flat_normals = normals.reshape(n_pixels, 3)
    penalty = lam * fourier_penalty(M)
    coeffs = np.empty((n_pixels, 3, n_coeffs), dtype=np.float64)
    with _one_blas_thread():
        for batch in _pixel_batches(n_pixels, n_lights, n_coeffs):
            design = _features(light_dirs, flat_normals[batch], view, M, clamp_diffuse)
            observed = targets[:, batch].astype(np.float64).transpose(1, 0, 2)  # (P, n, 3)
            solution = _SOLVERS[solver](design, observed, penalty)  # (P, K, 3)
            coeffs[batch] = solution.transpose(0, 2, 1)
    return coeffs.reshape(height, width, 3, n_coeffs)


def _render_kernel(coeffs, light_dirs, normals, view, M, clamp_diffuse) -> np.ndarray:
    height, width, _, n_coeffs = coeffs.shape
    n_pixels = height * width
    flat_coeffs = coeffs.reshape(n_pixels, 3, n_coeffs)
    flat_normals = normals.reshape(n_pixels, 3)
    out = np.empty((len(light_dirs), n_pixels, 3), dtype=np.float32)
    for batch in _pixel_batches(n_pixels, len(light_dirs), n_coeffs):
        design = _features(light_dirs, flat_normals[batch], view, M, clamp_diffuse)
        # (P, n, K) x (P, 3, K) -> (n, P, 3)
        out[:, batch] = np.einsum("pnk,pck->npc", design, flat_coeffs[batch])
    return out.reshape(len(light_dirs), height, width, 3)


def fourier_features(
    light_dirs, normals, M: int, view=VIEW, clamp_diffuse: bool = False
) -> np.ndarray:
    """Eq. 16 basis functions at every pixel for every light.

    Parameters
    ----------
    light_dirs : array_like of shape (n, 3)
        Directions towards the light (normalized here).
    normals : array_like of shape (H, W, 3)
    M : int
        Highest harmonic.
    view : array_like of shape (3,)
        Direction towards the camera; (0, 0, 1) for the paper's orthographic setting.
    clamp_diffuse : bool
        Use max(cos θd, 0) instead of the paper's cos θd.

    Returns
    -------
    ndarray of shape (n, H, W, 2M + 2), float64
    """
    dirs, normals, M, view = _check_geometry(light_dirs, normals, M, view)
    height, width, _ = normals.shape
    design = _features(dirs, normals.reshape(-1, 3), view, M, clamp_diffuse)
    return design.transpose(1, 0, 2).reshape(len(dirs), height, width, 2 * M + 2)


def design_condition(
    light_dirs, normals, M: int, view=VIEW, clamp_diffuse: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Condition number of each pixel's unregularized design matrix A (eq. 17).

    Parameters as :func:`fourier_features`.

    Returns
    -------
    cond : ndarray of shape (H, W), float64
        σ_max / σ_min of the (n, 2M + 2) matrix A; inf where σ_min is exactly 0.
    truncated : ndarray of shape (H, W), bool
        Where ``np.linalg.lstsq`` (and the λ = 0 fit) drops a singular value as
        round-off: the pixel is numerically rank-deficient (e.g. normal = view).
    """
    dirs, normals, M, view = _check_geometry(light_dirs, normals, M, view)
    height, width, _ = normals.shape
    flat = normals.reshape(-1, 3)
    n_coeffs = 2 * M + 2
    singular = np.empty((len(flat), min(len(dirs), n_coeffs)))
    with _one_blas_thread():
        for batch in _pixel_batches(len(flat), len(dirs), n_coeffs):
            design = _features(dirs, flat[batch], view, M, clamp_diffuse)
            singular[batch] = np.linalg.svd(design, compute_uv=False)
    with np.errstate(divide="ignore"):
        cond = singular[:, 0] / singular[:, -1]
    truncated = singular[:, -1] <= _lstsq_cutoff(len(dirs), n_coeffs) * singular[:, 0]
    return cond.reshape(height, width), truncated.reshape(height, width)


def _check_order(M) -> int:
    if isinstance(M, bool) or int(M) != M or M < 0:
        raise ConfigError(f"M (highest harmonic) must be an integer >= 0, got {M!r}")
    return int(M)


def _check_geometry(light_dirs, normals, M, view):
    """Checked (lights (n, 3), normals (H, W, 3), M, view (3,)) of one fit's geometry."""
    dirs, _ = check_dirs(light_dirs)
    return dirs, _check_normals(normals), _check_order(M), _check_view(view)


def fit_fourier(
    images,
    light_dirs,
    normals,
    view=VIEW,
    M: int = 10,
    lam: float = 3.14,
    clamp_diffuse: bool = False,
    solver: str = "auto",
) -> np.ndarray:
    """Fit the eq. 16 Fourier-series BRDF at every pixel (eq. 19 regularized LSQ).

    Parameters
    ----------
    images : ndarray of shape (N, H, W, 3)
        Linear RGB under each light.
    light_dirs : array_like of shape (N, 3)
        Directions towards the light, camera frame.
    normals : array_like of shape (H, W, 3) or (3,)
        Surface normals (a single normal is used at every pixel).
    view : array_like of shape (3,)
        Direction towards the camera, the same at every pixel (orthographic).
    M : int
        Highest harmonic; the paper picks 10. Needs N >= 2M + 2 (eq. 19 text).
    lam : float
        λ >= 0 of eq. 19; the paper picks 3.14. Scale-free: the penalty and the squared
        residuals scale alike with the image intensity, but both grow with N.
    clamp_diffuse : bool
        Use max(cos θd, 0) as the diffuse basis (not in the paper); pass the same value
        to :func:`render_fourier`.
    solver : {"auto", "normal", "svd"}
        "auto" (default): "svd" at λ = 0 (plain least squares, equal to
        ``np.linalg.lstsq``), "normal" at λ > 0 (:func:`resolve_solver`).
        "normal": batched normal equations (fast; exact for cond(A) up to ~1e7, a
        minimum-norm truncation beyond). "svd": batched SVD of the augmented system,
        as accurate as ``np.linalg.lstsq`` but slower.

    Returns
    -------
    coeffs : ndarray of shape (H, W, 3, 2M + 2), float64
        float64 because unregularized high-M fits have large, cancelling coefficients
        that float32 cannot hold without ruining the renders.
        Per pixel and channel: [a_d, a_0, a_1, b_1, ..., a_M, b_M].

    Raises
    ------
    ConfigError
        Shapes that disagree, M < 0, λ < 0, or N < 2M + 2.
    """
    dirs, _ = check_dirs(light_dirs)
    images = check_images(images, len(dirs))
    M = _check_order(M)
    if not np.isfinite(lam) or lam < 0:
        raise ConfigError(f"lam (regularization λ) must be finite and >= 0, got {lam!r}")
    if len(dirs) < 2 * M + 2:
        raise ConfigError(
            f"the Fourier model with M={M} needs N >= 2M + 2 = {2 * M + 2} images, "
            f"got N={len(dirs)}"
        )
    solver = resolve_solver(solver, float(lam))
    normals = _check_normals(normals, images.shape[1:3])
    return _fit_kernel(
        images, dirs, normals, _check_view(view), M, float(lam), clamp_diffuse, solver
    )


def render_fourier(
    coeffs, light_dirs, normals, view=VIEW, clamp_diffuse: bool = False
) -> np.ndarray:
    """Evaluate fitted Fourier coefficients under new lights.

    Parameters
    ----------
    coeffs : ndarray of shape (H, W, 3, 2M + 2)
    light_dirs : array_like of shape (3,) or (n, 3)
    normals : array_like of shape (H, W, 3) or (3,)
        May differ from the fitting normals: this is how a coefficient map is rendered
        on another shape (the optical pattern, eq. 20).
    view : array_like of shape (3,)
    clamp_diffuse : bool
        As in :func:`fit_fourier`.

    Returns
    -------
    ndarray of shape (H, W, 3) for one light, (n, H, W, 3) for several; float32
    """
    coeffs = check_coeffs(coeffs)
    if coeffs.shape[3] < 2 or coeffs.shape[3] % 2:
        raise ConfigError(f"Fourier coeffs need an even K = 2M + 2 >= 2, got {coeffs.shape[3]}")
    dirs, single = check_dirs(light_dirs)
    normals = _check_normals(normals, coeffs.shape[:2])
    M = (coeffs.shape[3] - 2) // 2
    out = _render_kernel(coeffs, dirs, normals, _check_view(view), M, clamp_diffuse)
    return out[0] if single else out


def rms_error(pred, target, mask=None) -> float:
    """Root-mean-square difference over all pixels, channels (and images).

    Parameters
    ----------
    pred, target : ndarray, same shape (..., H, W, C)
    mask : ndarray of shape (H, W), bool, optional
        Only pixels where the mask is True count.
    """
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ConfigError(f"pred {pred.shape} and target {target.shape} differ in shape")
    diff2 = (pred - target) ** 2
    if mask is None:
        return float(np.sqrt(diff2.mean()))
    mask = np.asarray(mask, dtype=bool)
    if pred.ndim < 3 or mask.shape != pred.shape[-3:-1]:
        raise ConfigError(f"mask {mask.shape} does not match the pixels of {pred.shape}")
    if not mask.any():
        raise ConfigError("mask selects no pixels")
    return float(np.sqrt(diff2[..., mask, :].mean()))
