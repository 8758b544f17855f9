"""Built-in synthetic light stack: a Bizen-ware pot under a grid of lights (method C).

The scene (PAPERS.md C, DESIGN.md "Built-in synthetic data"):

- an orthographic camera looking down -z (view (0, 0, 1)); camera frame x right,
  y up; image row 0 is the top;
- a pot (a surface of revolution about the image's vertical axis) in front of a dark
  matte backdrop, so every pixel has a known unit normal;
- three reflectance regions with a ground-truth map: 0 backdrop (dark grey, matte),
  1 ground (matte brown, Lambertian), 2 streaks (glossy red: Lambertian plus a Phong
  lobe in the angle θs between the mirrored light and the view, after Bizen *hidasuki*);
  albedo, lobe strength and exponent vary smoothly inside each region (texture);
- training lights on the paper's grid (:func:`grid_light_dirs`, 6 x 55 at 3°) and
  random held-out lights in the same range (:func:`heldout_light_dirs`).

Ground truth is :meth:`SyntheticScene.render`, usable at any light.

On disk (:func:`write_synthetic_stack`), in the real RTI layout so that the real reader
(:func:`pipeline.data.light_stack.load_light_stack`) is what reads it::

    root/
        lights.lp               training lights (RTI .lp)
        light_000.png ...       training images (8-bit sRGB PNG, or linear float EXR)
        normals.npy             (H, W, 3) float32 unit normals
        regions.npy             (H, W) uint8 region labels (0 backdrop, 1 ground, 2 streak)
        scene.json              the generator's settings: rebuild the scene with
                                :func:`load_synthetic_scene`
        heldout/
            heldout.lp          held-out lights
            light_000.png ...   noise-free renders under them

Training images carry Gaussian camera noise (``noise_std``, linear units, seeded);
held-out images do not, so they measure the model error alone.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from pipeline.core.errors import ConfigError, DataError
from pipeline.data.images import srgb_oetf, write_image_8bit
from pipeline.data.light_stack import write_lp

REGION_NAMES = ("backdrop", "ground", "streak")


@dataclass
class SyntheticStackConfig:
    """Settings of the synthetic pot; every field is recorded in ``scene.json``.

    Attributes
    ----------
    size : (int, int)
        (H, W) in pixels.
    seed : int
        Seed of ``np.random.default_rng`` for the streak layout, textures, held-out
        lights and camera noise.
    n_elevations, n_azimuths : int
        Training grid (paper: 6 x 55).
    azimuth_step_deg : float
        Lateral spacing of the grid (paper: 3°); the grid is centred on the camera.
    elevation_range_deg : (float, float)
        Lowest and highest light elevation above the horizontal plane, in degrees.
    n_heldout : int
        Random held-out lights inside the grid's range.
    n_streaks : int
        Number of red streaks.
    noise_std : float
        Gaussian camera noise on the training images (linear RGB units).
    image_format : str
        "png" (8-bit sRGB) or "exr" (linear float32).
    """

    size: tuple[int, int] = (128, 128)
    seed: int = 0
    n_elevations: int = 6
    n_azimuths: int = 55
    azimuth_step_deg: float = 3.0
    elevation_range_deg: tuple[float, float] = (10.0, 60.0)
    n_heldout: int = 12
    n_streaks: int = 3
    noise_std: float = 0.005
    image_format: str = "png"

    def validated(self) -> SyntheticStackConfig:
        """A copy with tuples normalized; ConfigError naming the first bad field."""
        size = (self.size, self.size) if np.isscalar(self.size) else tuple(self.size)
        if len(size) != 2 or min(size) < 16:
            raise ConfigError(f"size must be (H, W) with both >= 16, got {self.size!r}")
        for name in ("n_elevations", "n_azimuths"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        half_span = 0.5 * (self.n_azimuths - 1) * self.azimuth_step_deg
        if not 0 <= half_span < 90:
            raise ConfigError(
                f"n_azimuths={self.n_azimuths} x azimuth_step_deg={self.azimuth_step_deg} "
                "must span less than 180° so every light is in front of the pot"
            )
        low, high = self.elevation_range_deg
        if not 0 <= low <= high < 90:
            raise ConfigError(
                f"elevation_range_deg must satisfy 0 <= low <= high < 90, "
                f"got {self.elevation_range_deg!r}"
            )
        if self.n_heldout < 0 or self.n_streaks < 0 or self.noise_std < 0:
            raise ConfigError(
                "n_heldout, n_streaks and noise_std must be >= 0, got "
                f"{self.n_heldout}, {self.n_streaks}, {self.noise_std}"
            )
        if self.image_format not in ("png", "exr"):
            raise ConfigError(f"image_format must be 'png' or 'exr', got {self.image_format!r}")
        size, elevations = (int(size[0]), int(size[1])), (float(low), float(high))
        return replace(self, size=size, elevation_range_deg=elevations)


@dataclass
class SyntheticScene:
    """The pot's geometry and reflectance; :meth:`render` is the ground truth.

    Attributes
    ----------
    normals : ndarray of shape (H, W, 3), float32
    regions : ndarray of shape (H, W), uint8
        Labels into :data:`REGION_NAMES`.
    diffuse : ndarray of shape (H, W, 3), float32
        Lambertian albedo.
    specular : ndarray of shape (H, W, 3), float32
        Peak of the Phong lobe (zero outside the streaks).
    shininess : ndarray of shape (H, W), float32
        Phong exponent.
    config : SyntheticStackConfig
    """

    normals: np.ndarray
    regions: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    shininess: np.ndarray
    config: SyntheticStackConfig = field(default_factory=SyntheticStackConfig)

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels on the pot."""
        return self.regions > 0

    def render(self, light_dirs) -> np.ndarray:
        """Noise-free linear RGB under lights (3,) -> (H, W, 3) or (n, 3) -> (n, H, W, 3).

        I = ρ_d max(n·l, 0) + ρ_s max(cos θs, 0)^s [n·l > 0], view (0, 0, 1).
        """
        dirs = np.asarray(light_dirs, dtype=np.float64)
        single = dirs.ndim == 1
        dirs = np.atleast_2d(dirs)
        if dirs.ndim != 2 or dirs.shape[1] != 3:
            raise ConfigError(f"light_dirs must have shape (3,) or (n, 3), got {dirs.shape}")
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        normals = self.normals.astype(np.float64)
        out = np.empty((len(dirs), *self.regions.shape, 3), dtype=np.float32)
        for index, light in enumerate(dirs):  # a loop over lights, not pixels
            cos_d = normals @ light
            cos_s = 2.0 * cos_d * normals[..., 2] - light[2]  # r·v with v = (0, 0, 1)
            lobe = np.where(cos_d > 0, np.maximum(cos_s, 0.0) ** self.shininess, 0.0)
            out[index] = (
                self.diffuse * np.maximum(cos_d, 0.0)[..., None] + self.specular * lobe[..., None]
            )
        return out[0] if single else out


def _direction(azimuth_deg, elevation_deg) -> np.ndarray:
    """Unit vectors for lateral angle α about the vertical axis and elevation β."""
    alpha, beta = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack(
        [np.sin(alpha) * np.cos(beta), np.sin(beta), np.cos(alpha) * np.cos(beta)], axis=-1
    )


def grid_light_dirs(config: SyntheticStackConfig) -> np.ndarray:
    """Training lights, shape (n_elevations * n_azimuths, 3), elevation-major order."""
    config = config.validated()
    low, high = config.elevation_range_deg
    elevations = np.linspace(low, high, config.n_elevations)
    azimuths = (
        np.arange(config.n_azimuths) - 0.5 * (config.n_azimuths - 1)
    ) * config.azimuth_step_deg
    beta, alpha = np.meshgrid(elevations, azimuths, indexing="ij")
    return _direction(alpha.ravel(), beta.ravel())


def heldout_light_dirs(config: SyntheticStackConfig, rng: np.random.Generator) -> np.ndarray:
    """Held-out lights, shape (n_heldout, 3), uniform in the grid's angular range."""
    config = config.validated()
    half_span = 0.5 * (config.n_azimuths - 1) * config.azimuth_step_deg
    low, high = config.elevation_range_deg
    return _direction(
        rng.uniform(-half_span, half_span, config.n_heldout),
        rng.uniform(low, high, config.n_heldout),
    )


def _pot_radius(y: np.ndarray) -> np.ndarray:
    """Radius of the pot at height y (image half-height = 1): belly, neck and lip."""
    belly = 0.40 * np.exp(-(((y + 0.15) / 0.50) ** 2))
    lip = 0.10 * np.exp(-(((y - 0.80) / 0.08) ** 2))
    return 0.30 + belly + lip


def _smooth_noise(rng: np.random.Generator, shape, sigma: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field: texture inside a region."""
    field_ = gaussian_filter(rng.normal(size=shape), sigma, mode="wrap")
    return field_ / (field_.std() + 1e-12)


def make_synthetic_scene(config: SyntheticStackConfig | None = None) -> SyntheticScene:
    """Build the pot: normals, region map and reflectance maps (deterministic in seed)."""
    config = (config or SyntheticStackConfig()).validated()
    rng = np.random.default_rng(config.seed)
    height, width = config.size
    # Square pixels; the image spans y in [-1, 1] top to bottom-reversed.
    y = 1.0 - (np.arange(height) + 0.5) * (2.0 / height)
    x = (np.arange(width) + 0.5 - 0.5 * width) * (2.0 / height)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    radius = _pot_radius(yy)
    step = 1e-4
    radius_slope = (_pot_radius(yy + step) - _pot_radius(yy - step)) / (2 * step)
    on_pot = (np.abs(xx) < radius) & (yy > -0.92) & (yy < 0.86)
    depth = np.sqrt(np.maximum(radius**2 - xx**2, 0.0))
    # Gradient of x² + z² - R(y)²: (x, -R R', z).
    normals = np.stack([xx, -radius * radius_slope, depth], axis=-1)
    normals[~on_pot] = (0.0, 0.0, 1.0)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)

    # Streaks live on the pot's surface: u = angle around the axis, v = height.
    u = np.arcsin(np.clip(xx / radius, -1.0, 1.0))
    streak = np.zeros((height, width), dtype=bool)
    for _ in range(config.n_streaks):
        centre = rng.uniform(-0.6, 0.6)
        slope = rng.uniform(-0.45, 0.45)
        amplitude = rng.uniform(0.05, 0.15)
        frequency = rng.uniform(1, 3)
        phase = rng.uniform(0, 6.3)
        half_width = rng.uniform(0.10, 0.16) * (1 + 0.3 * np.sin(2.1 * u + phase))
        centre_line = centre + slope * u + amplitude * np.sin(frequency * u + phase)
        streak |= np.abs(yy - centre_line) < half_width
    regions = np.zeros((height, width), dtype=np.uint8)
    regions[on_pot] = 1
    regions[on_pot & streak] = 2

    texture = _smooth_noise(rng, (height, width), 1.5)
    blotches = _smooth_noise(rng, (height, width), 6.0)
    grain = 1.0 + 0.10 * texture + 0.08 * blotches
    colour = {0: (0.06, 0.06, 0.07), 1: (0.42, 0.27, 0.16), 2: (0.55, 0.10, 0.05)}
    diffuse = np.zeros((height, width, 3))
    for label, rgb in colour.items():
        diffuse[regions == label] = rgb
    diffuse[on_pot] *= grain[on_pot, None]
    specular = np.zeros((height, width, 3))
    shininess = np.full((height, width), 1.0)
    glossy = regions == 2
    gloss_noise = _smooth_noise(rng, (height, width), 3.0)
    specular[glossy] = 0.30 * (1.0 + 0.2 * gloss_noise[glossy, None]) * np.array([1.0, 0.85, 0.8])
    shininess[glossy] = 20.0 * (1.0 + 0.2 * gloss_noise[glossy])
    return SyntheticScene(
        normals=normals.astype(np.float32),
        regions=regions,
        diffuse=np.clip(diffuse, 0.0, 1.0).astype(np.float32),
        specular=np.clip(specular, 0.0, 1.0).astype(np.float32),
        shininess=shininess.astype(np.float32),
        config=config,
    )


def _write_image(path: Path, linear_rgb: np.ndarray) -> None:
    if path.suffix == ".exr":
        import OpenEXR

        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        channels = {
            c: np.ascontiguousarray(linear_rgb[..., i], dtype=np.float32)
            for i, c in enumerate("RGB")
        }
        OpenEXR.File(header, channels).write(str(path))
    else:  # unsynced: the staging folder is published as a whole
        write_image_8bit(path, srgb_oetf(linear_rgb), sync=False)


def _write_images(
    folder: Path, lp_name: str, images: np.ndarray, dirs: np.ndarray, suffix: str
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"light_{index:03d}.{suffix}" for index in range(len(images))]
    for name, image in zip(names, images, strict=True):
        _write_image(folder / name, image)
    write_lp(folder / lp_name, names, dirs)


def write_synthetic_stack(
    root: str | os.PathLike, size=(128, 128), seed: int = 0, overwrite: bool = False, **settings
) -> SyntheticScene:
    """Render the synthetic pot and write it in the RTI layout (module docstring).

    The folder appears complete or not at all: everything is written into a temporary
    sibling folder that is renamed to ``root`` last.

    Parameters
    ----------
    root : path-like
        Folder to create.
    size : int or (int, int)
        (H, W) in pixels.
    seed : int
    overwrite : bool
        Replace an existing ``root``; otherwise an existing one is a ConfigError.
    **settings
        Other :class:`SyntheticStackConfig` fields (n_elevations, n_azimuths, ...).

    Returns
    -------
    SyntheticScene
        The ground truth, also recoverable with :func:`load_synthetic_scene`.
    """
    root = Path(root)
    unknown = set(settings) - set(SyntheticStackConfig.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"unknown synthetic-stack settings {sorted(unknown)}")
    config = SyntheticStackConfig(size=size, seed=seed, **settings).validated()
    if root.exists() and not overwrite:
        raise ConfigError(f"{root} already exists; pass overwrite=True to replace it")
    scene = make_synthetic_scene(config)
    # The scene used its own generator; the lights and noise draw from a second stream
    # of the same seed so that changing n_heldout does not move the streaks.
    rng = np.random.default_rng([config.seed, 1])
    train_dirs = grid_light_dirs(config)
    heldout_dirs = heldout_light_dirs(config, rng)
    train = scene.render(train_dirs)
    train += rng.normal(0.0, config.noise_std, size=train.shape).astype(np.float32)

    root.parent.mkdir(parents=True, exist_ok=True)
    staging = root.parent / f".{root.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        _write_images(staging, "lights.lp", train, train_dirs, config.image_format)
        del train
        heldout = scene.render(heldout_dirs)
        _write_images(staging / "heldout", "heldout.lp", heldout, heldout_dirs, config.image_format)
        np.save(staging / "normals.npy", scene.normals)
        np.save(staging / "regions.npy", scene.regions)
        (staging / "scene.json").write_text(json.dumps(asdict(config), indent=2) + "\n")
        if root.exists():  # overwrite: move the old folder aside, then swap
            trash = root.parent / f".{root.name}.old-{uuid.uuid4().hex[:8]}"
            root.rename(trash)
            shutil.rmtree(trash, ignore_errors=True)
        staging.rename(root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return scene


def load_synthetic_scene(root: str | os.PathLike) -> SyntheticScene:
    """Rebuild the ground-truth scene of a folder written by :func:`write_synthetic_stack`."""
    path = Path(root) / "scene.json"
    try:
        settings = json.loads(path.read_text())
        config = SyntheticStackConfig(**settings)
    except (OSError, ValueError, TypeError) as exc:
        raise DataError(f"cannot read synthetic-scene settings {path}: {exc}") from exc
    return make_synthetic_scene(config)
