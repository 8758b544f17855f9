"""What the renderer draws: a triangle mesh with uv and tangent frames, a camera, lights.

World space is right-handed with +y up; lengths have no unit (the default scene is about
two units across). Every vertex carries a uv coordinate and an orthonormal tangent frame
(tangent t along +u, normal n, bitangent b = n x t, which points along +v), the frame the
BTF's directions are measured in (see :mod:`pipeline.render.engine`). Every triangle
carries a material id: :data:`CLOTH` triangles are shaded with the material given to
:func:`pipeline.render.engine.render`, :data:`FLOOR` triangles with a uniform Lambertian
of albedo :attr:`Scene.floor_albedo`.

Triangles are wound so that their geometric normal ``(v1 - v0) x (v2 - v0)`` points to
the same side as the vertex normals.

Examples
--------
>>> scene = default_scene(32, 24)
>>> scene.mesh.vertices.shape[1], scene.camera.width, scene.camera.height
(3, 32, 24)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

CLOTH = 0  # shaded with the render's material (the BTF)
FLOOR = 1  # shaded with the scene's uniform Lambertian floor
MATERIAL_IDS = (CLOTH, FLOOR)


def _vector3(value, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name}={value!r} must be 3 finite numbers")
    return array


def normalized(vectors: np.ndarray) -> np.ndarray:
    """``vectors`` (..., 3) divided by their lengths."""
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh with per-vertex uv and tangent frames and per-triangle materials.

    Attributes
    ----------
    vertices : ndarray of shape (V, 3), float32
    triangles : ndarray of shape (F, 3), int32, indices into ``vertices``.
    uv : ndarray of shape (V, 2), float64; the BTF crop repeats every unit of u and v.
    normals : ndarray of shape (V, 3), float64, unit.
    tangents : ndarray of shape (V, 3), float64, unit and orthogonal to ``normals``.
    material_ids : ndarray of shape (F,), int32, each :data:`CLOTH` or :data:`FLOOR`.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    material_ids: np.ndarray

    def __post_init__(self):
        vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        n_vertices = len(vertices)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or n_vertices == 0:
            raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {vertices.shape}")
        if not np.all(np.isfinite(vertices)):
            raise ValueError("vertices must be finite")
        triangles = np.asarray(self.triangles)
        if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
            raise ValueError(f"triangles must have shape (F, 3) with F > 0, got {triangles.shape}")
        if not np.issubdtype(triangles.dtype, np.integer):
            raise ValueError(f"triangles must be integers, got {triangles.dtype}")
        if triangles.min() < 0 or triangles.max() >= n_vertices:
            raise ValueError(f"triangles index vertices outside [0, {n_vertices})")
        set_ = object.__setattr__  # frozen: store the checked, converted arrays
        for name, width in (("uv", 2), ("normals", 3), ("tangents", 3)):
            array = np.asarray(getattr(self, name), dtype=np.float64)
            if array.shape != (n_vertices, width):
                raise ValueError(
                    f"{name} must have shape ({n_vertices}, {width}), got {array.shape}"
                )
            set_(self, name, array)
        material_ids = np.asarray(self.material_ids)
        if material_ids.shape != (len(triangles),):
            raise ValueError(
                f"material_ids must have shape ({len(triangles)},), got {material_ids.shape}"
            )
        if not np.isin(material_ids, MATERIAL_IDS).all():
            bad = material_ids[~np.isin(material_ids, MATERIAL_IDS)][0]
            raise ValueError(f"material id {bad} is not one of {list(MATERIAL_IDS)}")
        set_(self, "vertices", vertices)
        set_(self, "triangles", np.ascontiguousarray(triangles, dtype=np.int32))
        set_(self, "material_ids", material_ids.astype(np.int32))

    @property
    def bitangents(self) -> np.ndarray:
        """ndarray of shape (V, 3): normal x tangent, along +v."""
        return np.cross(self.normals, self.tangents)

    def face_normals(self) -> np.ndarray:
        """Unit geometric normals ``(v1 - v0) x (v2 - v0)``, ndarray of shape (F, 3)."""
        corners = self.vertices.astype(np.float64)[self.triangles]
        return normalized(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))


def merge_meshes(*meshes: Mesh) -> Mesh:
    """One mesh holding all the triangles of ``meshes``, in order."""
    if not meshes:
        raise ValueError("merge_meshes needs at least one mesh")
    offsets = np.cumsum([0] + [len(mesh.vertices) for mesh in meshes[:-1]])
    triangles = [mesh.triangles + o for mesh, o in zip(meshes, offsets, strict=True)]
    names = ("vertices", "uv", "normals", "tangents", "material_ids")
    merged = {name: np.concatenate([getattr(mesh, name) for mesh in meshes]) for name in names}
    return Mesh(triangles=np.concatenate(triangles), **merged)


def quad(corner, edge_u, edge_v, *, tiles: float = 1.0, material_id: int = CLOTH) -> Mesh:
    """A flat parallelogram of two triangles: ``corner + s * edge_u + t * edge_v``.

    Parameters
    ----------
    corner, edge_u, edge_v : array_like of shape (3,)
        The corner at uv (0, 0) and the edges along which u and v grow.
    tiles : float
        uv runs over [0, tiles] along each edge.
    material_id : :data:`CLOTH` or :data:`FLOOR`.

    Returns
    -------
    Mesh
        Normal ``edge_u x edge_v`` (normalized), tangent along ``edge_u``.
    """
    corner = _vector3(corner, "corner")
    edge_u, edge_v = _vector3(edge_u, "edge_u"), _vector3(edge_v, "edge_v")
    normal = np.cross(edge_u, edge_v)
    if np.linalg.norm(normal) <= 1e-12 * np.linalg.norm(edge_u) * np.linalg.norm(edge_v):
        raise ValueError(f"edge_u={edge_u.tolist()} and edge_v={edge_v.tolist()} are parallel")
    if not tiles > 0:
        raise ValueError(f"tiles={tiles!r} must be > 0")
    normal = normal / np.linalg.norm(normal)
    tangent = edge_u - (edge_u @ normal) * normal
    st = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return Mesh(
        vertices=corner + st[:, :1] * edge_u + st[:, 1:] * edge_v,
        triangles=np.array([[0, 1, 2], [0, 2, 3]]),
        uv=st * tiles,
        normals=np.tile(normal, (4, 1)),
        tangents=np.tile(tangent / np.linalg.norm(tangent), (4, 1)),
        material_ids=np.full(2, material_id),
    )


def folded_sheet(
    resolution: int = 96,
    folds: int = 3,
    amplitude: float = 0.12,
    *,
    size: float = 2.0,
    droop: float = 0.6,
    tiles: float = 4.0,
    seed: int = 0,
) -> Mesh:
    """A square cloth draped over a horizontal bar, with folds running down its sides.

    The sheet is the height field ``y = h(x, z)`` over ``x, z`` in ``[-size/2, size/2]``::

        h = -droop * Z**2 + amplitude * (0.25 + 0.75 * Z**2) * (sin(A) + 0.3 * sin(B))
        A = pi * folds * X + phase_a + bend * Z,   B = 2 * pi * folds * X + phase_b

    with X = 2x / size, Z = 2z / size: a parabolic droop on both sides of the bar (along x
    at z = 0), and ``folds`` fold ridges across the width whose depth grows towards the hems
    and which fan out slightly (``bend``); the phases and ``bend`` come from ``seed``.
    Normals and tangents are analytic (from the gradient of h).

    Parameters
    ----------
    resolution : int
        Quads along each side (``(resolution + 1) ** 2`` vertices), >= 1.
    folds : int
        Fold ridges across the width, >= 0.
    amplitude : float
        Height of the folds at the hems, >= 0.
    size, droop : float
        Side of the square (> 0) and how far its hems hang below the bar (>= 0).
    tiles : float
        uv spans [0, tiles] along each side, so the BTF crop repeats ``tiles`` times.
    seed : int
        Seeds the phases and the fanning of the folds.

    Returns
    -------
    Mesh
        All triangles :data:`CLOTH`; u grows with x, v with -z (the normal points up).
    """
    for name, value, low in (("resolution", resolution, 1), ("folds", folds, 0)):
        if int(value) != value or value < low:
            raise ValueError(f"{name}={value!r} must be an integer >= {low}")
    for name, value in (("size", size), ("tiles", tiles)):
        if not value > 0:
            raise ValueError(f"{name}={value!r} must be > 0")
    for name, value in (("amplitude", amplitude), ("droop", droop)):
        if not value >= 0:
            raise ValueError(f"{name}={value!r} must be >= 0")
    rng = np.random.default_rng(seed)
    phase_a, phase_b = rng.uniform(0.0, 2.0 * np.pi, size=2)
    bend = rng.uniform(-1.0, 1.0)
    omega = np.pi * folds

    s = np.linspace(0.0, 1.0, resolution + 1)
    t_grid, s_grid = np.meshgrid(s, s, indexing="ij")  # rows of the grid follow v
    big_x, big_z = 2.0 * s_grid - 1.0, 1.0 - 2.0 * t_grid
    a = omega * big_x + phase_a + bend * big_z
    b = 2.0 * omega * big_x + phase_b
    envelope = 0.25 + 0.75 * big_z**2
    wave = np.sin(a) + 0.3 * np.sin(b)
    height = -droop * big_z**2 + amplitude * envelope * wave
    dh_dx = amplitude * envelope * (omega * np.cos(a) + 0.6 * omega * np.cos(b))
    dh_dz = -2.0 * droop * big_z + amplitude * (1.5 * big_z * wave + envelope * bend * np.cos(a))
    half = size / 2.0
    positions = np.stack([big_x * half, height, big_z * half], axis=-1)
    # dP/du ~ (1, dh/dX, 0) and dP/dv ~ (0, -dh/dZ, -1) (X, Z in the same units as h / half).
    d_du = np.stack([np.full_like(dh_dx, half), dh_dx, np.zeros_like(dh_dx)], axis=-1)
    d_dv = np.stack([np.zeros_like(dh_dz), -dh_dz, np.full_like(dh_dz, -half)], axis=-1)
    normals = normalized(np.cross(d_du, d_dv))
    tangents = normalized(d_du)  # orthogonal to the normal already

    n = resolution + 1
    index = np.arange(n * n).reshape(n, n)
    a00, a01 = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    a11, a10 = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    triangles = np.concatenate([np.stack([a00, a01, a11], 1), np.stack([a00, a11, a10], 1)])
    return Mesh(
        vertices=positions.reshape(-1, 3),
        triangles=triangles,
        uv=np.stack([s_grid, t_grid], axis=-1).reshape(-1, 2) * tiles,
        normals=normals.reshape(-1, 3),
        tangents=tangents.reshape(-1, 3),
        material_ids=np.full(len(triangles), CLOTH),
    )


@dataclass(frozen=True)
class Camera:
    """A pinhole camera; pixel (0, 0) is the top-left one, x grows to the right.

    Attributes
    ----------
    position, look_at, up : array_like of shape (3,)
    fov_y_degrees : float, the vertical field of view, in (0, 180).
    width, height : int, the image size in pixels.
    """

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov_y_degrees: float
    width: int
    height: int

    def __post_init__(self):
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, _vector3(getattr(self, name), name))
        forward = self.look_at - self.position
        if np.linalg.norm(forward) == 0:
            raise ValueError("camera position and look_at coincide")
        if np.linalg.norm(np.cross(forward, self.up)) <= 1e-9 * np.linalg.norm(forward):
            raise ValueError(f"camera up={self.up.tolist()} is parallel to the view direction")
        if not 0 < self.fov_y_degrees < 180:
            raise ValueError(f"fov_y_degrees={self.fov_y_degrees!r} must be in (0, 180)")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"camera {name}={value!r} must be an integer >= 1")

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit (right, up, forward) vectors of the camera, each of shape (3,)."""
        forward = normalized(self.look_at - self.position)
        right = normalized(np.cross(forward, self.up))
        return right, np.cross(right, forward), forward

    def rays(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through image points given in pixels (x in [0, width], y in [0, height]).

        Parameters
        ----------
        x, y : ndarray of shape (n,), continuous pixel coordinates (pixel (i, j) covers
            x in [j, j + 1], y in [i, i + 1]).

        Returns
        -------
        origins, directions : ndarrays of shape (n, 3), float64; directions are unit.
        """
        right, up, forward = self.basis()
        half_height = np.tan(np.radians(self.fov_y_degrees) / 2.0)
        half_width = half_height * self.width / self.height
        sx = (2.0 * np.asarray(x, dtype=np.float64) / self.width - 1.0) * half_width
        sy = (1.0 - 2.0 * np.asarray(y, dtype=np.float64) / self.height) * half_height
        directions = normalized(forward + sx[:, None] * right + sy[:, None] * up)
        return np.broadcast_to(self.position, directions.shape).copy(), directions


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light: irradiance ``intensity / distance**2`` perpendicular to it.

    position : array_like of shape (3,); intensity : array_like of shape (3,), RGB >= 0.
    """

    position: np.ndarray
    intensity: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "position", _vector3(self.position, "position"))
        intensity = _vector3(self.intensity, "intensity")
        if np.any(intensity < 0):
            raise ValueError(f"intensity={intensity.tolist()} must be >= 0")
        object.__setattr__(self, "intensity", intensity)


@dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity, such as the sun.

    direction : array_like of shape (3,), towards the light (normalized on creation).
    irradiance : array_like of shape (3,), RGB >= 0, on a surface facing the light.
    """

    direction: np.ndarray
    irradiance: np.ndarray

    def __post_init__(self):
        direction = _vector3(self.direction, "direction")
        if np.linalg.norm(direction) == 0:
            raise ValueError("direction must not be the zero vector")
        irradiance = _vector3(self.irradiance, "irradiance")
        if np.any(irradiance < 0):
            raise ValueError(f"irradiance={irradiance.tolist()} must be >= 0")
        object.__setattr__(self, "direction", direction / np.linalg.norm(direction))
        object.__setattr__(self, "irradiance", irradiance)


Light = PointLight | DirectionalLight


@dataclass(frozen=True)
class Scene:
    """A mesh, a camera and lights.

    Attributes
    ----------
    mesh : Mesh
    camera : Camera
    lights : tuple of PointLight and DirectionalLight, at least one.
    floor_albedo : ndarray of shape (3,), in [0, 1]: the Lambertian of :data:`FLOOR`.
    """

    mesh: Mesh
    camera: Camera
    lights: tuple = field(default_factory=tuple)
    floor_albedo: np.ndarray = field(default_factory=lambda: np.full(3, 0.5))

    def __post_init__(self):
        lights = tuple(self.lights)
        if not lights:
            raise ValueError("a scene needs at least one light")
        for light in lights:
            if not isinstance(light, PointLight | DirectionalLight):
                raise ValueError(f"light {light!r} is neither a PointLight nor a DirectionalLight")
        albedo = _vector3(self.floor_albedo, "floor_albedo")
        if np.any((albedo < 0) | (albedo > 1)):
            raise ValueError(f"floor_albedo={albedo.tolist()} must be in [0, 1]")
        object.__setattr__(self, "lights", lights)
        object.__setattr__(self, "floor_albedo", albedo)


LIGHT_SETTINGS = ("point", "directional", "both")


def default_scene(
    width: int = 256,
    height: int = 256,
    lights: str | Sequence[Light] = "point",
    *,
    floor: bool = True,
    resolution: int = 96,
    tiles: float = 4.0,
    seed: int = 0,
) -> Scene:
    """The Fig. 8 scene: :func:`folded_sheet` seen from the front and above.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    lights : ``"point"``, ``"directional"``, ``"both"``, or a sequence of lights
        The key light from the front left and above, as a point light placed so that its
        irradiance at the centre of the sheet is 1 (per channel), as a directional light
        of irradiance 1 from the same direction, or both at half strength each.
    floor : bool
        Add a square :data:`FLOOR` below the hems (it catches the cloth's shadow).
    resolution, tiles, seed : passed to :func:`folded_sheet`.

    Returns
    -------
    Scene
    """
    sheet = folded_sheet(resolution, tiles=tiles, seed=seed)
    meshes = [sheet]
    if floor:
        y = float(sheet.vertices[:, 1].min()) - 0.15
        meshes.append(quad([-4.0, y, 4.0], [8.0, 0.0, 0.0], [0.0, 0.0, -8.0], material_id=FLOOR))
    camera = Camera(
        position=[0.0, 2.0, 3.4],
        look_at=[0.0, -0.35, 0.0],
        up=[0.0, 1.0, 0.0],
        fov_y_degrees=35.0,
        width=width,
        height=height,
    )
    to_light = np.array([-1.0, 1.6, 1.2])
    distance = 3.0
    if isinstance(lights, str):
        if lights not in LIGHT_SETTINGS:
            raise ValueError(
                f"lights={lights!r} must be one of {list(LIGHT_SETTINGS)} or a sequence of lights"
            )
        scale = 0.5 if lights == "both" else 1.0
        position = distance * to_light / np.linalg.norm(to_light)
        point = PointLight(position, np.full(3, scale * distance**2))
        directional = DirectionalLight(to_light, np.full(3, scale))
        chosen = {"point": [point], "directional": [directional], "both": [point, directional]}
        lights = chosen[lights]
    return Scene(mesh=merge_meshes(*meshes), camera=camera, lights=tuple(lights))
