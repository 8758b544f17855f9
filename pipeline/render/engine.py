"""Direct lighting of a BTF-covered mesh with hard shadows, traced with Embree.

:func:`render` returns linear radiance per pixel: the mean over ``spp`` jittered camera
rays per pixel of the light reflected towards the camera at the first hit, from every
light that the hit point sees (no indirect light, no emission; a miss gives the
background colour).

Conventions
-----------
Tangent frame and directions
    At a hit, the vertex normals and tangents are interpolated with the barycentrics and
    re-orthonormalised: n (shading normal), t (tangent, along +u), b = n x t (bitangent,
    along +v). The material is queried with (theta_light, phi_light, theta_view, phi_view)
    in radians in that frame (:func:`~pipeline.render.materials.spherical`), light and
    view both pointing away from the surface.
uv to texel
    :func:`~pipeline.render.materials.texels_of_uv`: the crop repeats every unit of u and
    v. No filtering: each ray takes the texel it hits, and the jittered samples average
    over a pixel.
Units
    A material value is a BTF value, as in BTF images: radiance reflected towards the view
    per unit irradiance *on a surface perpendicular to the light*, so the cosine
    foreshortening of the light on the surface is already in it (for a Lambertian albedo
    rho the value is ``rho / pi * cos(theta_light)``). Each unshadowed light adds
    ``material value x E_perp`` to the radiance, with E_perp = intensity / distance**2 for
    a :class:`~pipeline.render.scene.PointLight` and the irradiance of a
    :class:`~pipeline.render.scene.DirectionalLight`. Negative material values (a neural
    decoder may produce them) are clamped at 0.
Visibility
    A light counts at a hit when the view and the light are both above the shading normal
    and above the triangle's geometric normal (a back face is black), and a shadow ray,
    leaving from the hit point moved ``epsilon`` along the geometric normal, reaches the
    light unblocked.
Batching
    Camera samples are processed in chunks of ``batch_rays`` (pass-major: all pixels of
    sample 0, then of sample 1, ...). All material queries of a chunk, every light
    included, go to the material in ONE ``evaluate`` call, since the material may be a
    neural decoder for which many small calls are slow.
Randomness
    Sub-pixel positions come from ``numpy.random.default_rng(seed)``, drawn chunk by chunk
    in sample order, so the image depends on ``seed`` and not on ``batch_rays``. The
    samples of a pixel are stratified (:func:`strata`, :func:`subpixel_offsets`).
Coverage
    ``RenderStats.lit_cloth``: per pixel, the fraction of its camera samples that landed
    on front-facing cloth seen by at least one light (1 wholly on lit cloth, below 1 at
    silhouettes, shadow edges and the floor); it does not depend on the material.

What this module relies on in ``embreex`` (checked with embreex 4.4.0.post1):
``EmbreeScene()``; ``TriangleMesh(scene, vertices (V, 3) float32, triangles (F, 3))``;
``scene.run(origins, directions, output=1)`` with float32 (n, 3) C-contiguous arrays
returns a dict with ``primID`` (-1 on a miss) and barycentrics ``u``, ``v`` (the hit is
``(1 - u - v) v0 + u v1 + v v2``); rays start at t = 0 (hence the offset of shadow rays)
and ``tfar`` is in units of the direction's length; ``scene.run(..., dists=tfar,
query="OCCLUDED")`` returns -1 for a ray that hits nothing before ``tfar`` (it writes
into ``dists``, so a fresh array is passed).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from pipeline.render.materials import spherical, texels_of_uv
from pipeline.render.scene import CLOTH, FLOOR, PointLight, Scene, normalized

DEFAULT_BATCH_RAYS = 1 << 18
# Shadow rays towards a point light stop this fraction short of it.
_SHADOW_STOP = 1.0 - 1e-6


@dataclass(frozen=True)
class RenderStats:
    """What one render cost.

    primary_rays : camera rays (width x height x spp).
    shadow_rays : rays traced towards lights.
    material_queries : (texel, direction pair) queries answered by the material.
    material_calls : calls of ``material.evaluate``.
    seconds : wall-clock time of the render.
    lit_cloth : ndarray (height, width), float32: the fraction of each pixel's camera
        samples on front-facing cloth lit by at least one light (module docstring).
    """

    primary_rays: int
    shadow_rays: int
    material_queries: int
    material_calls: int
    seconds: float
    lit_cloth: np.ndarray

    @property
    def rays(self) -> int:
        return self.primary_rays + self.shadow_rays

    @property
    def rays_per_second(self) -> float:
        return self.rays / self.seconds if self.seconds > 0 else math.inf


def render(
    scene: Scene,
    material,
    spp: int,
    seed: int,
    *,
    batch_rays: int = DEFAULT_BATCH_RAYS,
    background=(0.0, 0.0, 0.0),
    epsilon: float | None = None,
) -> np.ndarray:
    """Render ``scene`` with ``material`` on its cloth (see the module docstring).

    Parameters
    ----------
    scene : :class:`pipeline.render.scene.Scene`
    material : a :class:`pipeline.render.materials.Material` (anything with
        ``crop_size`` (rows, cols) and ``evaluate(texels (n,), directions (n, 4)) -> (n, 3)``),
        for the triangles of material id CLOTH.
    spp : int
        Camera samples per pixel, >= 1.
    seed : int
        Seeds the sub-pixel jitter.
    batch_rays : int
        Camera rays traced and shaded per chunk (bounds memory), >= 1.
    background : array_like of shape (3,)
        Radiance of a ray that hits nothing.
    epsilon : float or None
        Offset of shadow rays along the normal; None means 1e-4 times the diagonal of the
        mesh's bounding box.

    Returns
    -------
    ndarray of shape (height, width, 3), float32
        Linear radiance; row 0 is the top of the image.
    """
    return render_with_stats(
        scene, material, spp, seed, batch_rays=batch_rays, background=background, epsilon=epsilon
    )[0]


def render_with_stats(
    scene: Scene,
    material,
    spp: int,
    seed: int,
    *,
    batch_rays: int = DEFAULT_BATCH_RAYS,
    background=(0.0, 0.0, 0.0),
    epsilon: float | None = None,
) -> tuple[np.ndarray, RenderStats]:
    """:func:`render`, also returning a :class:`RenderStats`."""
    started = time.perf_counter()
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a pipeline.render.scene.Scene, got {type(scene).__name__}")
    if not callable(getattr(material, "evaluate", None)):
        raise ValueError(f"material {material!r} has no evaluate(texels, directions) method")
    crop = tuple(getattr(material, "crop_size", ()))
    if len(crop) != 2 or not all(int(v) == v and v >= 1 for v in crop):
        raise ValueError(f"material crop_size={crop!r} must be (rows, cols), both >= 1")
    for name, value in (("spp", spp), ("batch_rays", batch_rays)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ValueError(f"{name}={value!r} must be an integer >= 1")
    if isinstance(seed, bool) or int(seed) != seed:
        raise ValueError(f"seed={seed!r} must be an integer")
    background = np.asarray(background, dtype=np.float64)
    if background.shape != (3,) or not np.all(np.isfinite(background)):
        raise ValueError(f"background={background.tolist()!r} must be 3 finite numbers")
    if epsilon is not None and not epsilon > 0:
        raise ValueError(f"epsilon={epsilon!r} must be > 0")

    tracer = _Tracer(scene, epsilon)
    counted = _CountingMaterial(material)
    width, height = scene.camera.width, scene.camera.height
    n_pixels = width * height
    total = n_pixels * int(spp)
    sums = np.zeros((n_pixels, 3), dtype=np.float64)
    lit_cloth = np.zeros(n_pixels, dtype=np.int64)
    rng = np.random.default_rng(int(seed))
    shadow_rays = 0
    for start in range(0, total, int(batch_rays)):
        sample = np.arange(start, min(start + int(batch_rays), total))
        pixel = sample % n_pixels
        offset = subpixel_offsets(sample // n_pixels, int(spp), rng.random((len(sample), 2)))
        x = pixel % width + offset[:, 0]
        y = pixel // width + offset[:, 1]
        radiance, on_lit_cloth, traced = _shade(tracer, counted, x, y, background)
        shadow_rays += traced
        lit_cloth += np.bincount(pixel[on_lit_cloth], minlength=n_pixels)
        for channel in range(3):
            sums[:, channel] += np.bincount(pixel, radiance[:, channel], minlength=n_pixels)
    image = (sums / int(spp)).reshape(height, width, 3).astype(np.float32)
    stats = RenderStats(
        primary_rays=total,
        shadow_rays=shadow_rays,
        material_queries=counted.queries,
        material_calls=counted.calls,
        seconds=time.perf_counter() - started,
        lit_cloth=(lit_cloth / int(spp)).reshape(height, width).astype(np.float32),
    )
    return image, stats


def strata(spp: int) -> tuple[int, int]:
    """(a, b), a x b = spp strata across x and y, b the largest divisor <= sqrt(spp)
    (4 x 4 at 16 spp, 16 x 8 at 128, 1 x 1 at 1)."""
    b = next(d for d in range(math.isqrt(spp), 0, -1) if spp % d == 0)
    return spp // b, b


def subpixel_offsets(sample_index: np.ndarray, spp: int, uniform: np.ndarray) -> np.ndarray:
    """Offsets (n, 2) in [0, 1) of samples ``sample_index`` (n,) from uniforms (n, 2):
    sample s is jittered inside stratum (s mod a, s div a) of :func:`strata`."""
    a, b = strata(spp)
    stratum = np.column_stack([sample_index % a, sample_index // a])
    return (stratum + uniform) / np.array([a, b])


class _CountingMaterial:
    """Forwards ``evaluate`` and counts calls and queries."""

    def __init__(self, material):
        self.material = material
        self.crop_size = tuple(int(v) for v in material.crop_size)
        self.calls = 0
        self.queries = 0

    def evaluate(self, texels: np.ndarray, directions: np.ndarray) -> np.ndarray:
        self.calls += 1
        self.queries += len(texels)
        values = np.asarray(self.material.evaluate(texels, directions), dtype=np.float32)
        if values.shape != (len(texels), 3):
            raise ValueError(
                f"material.evaluate returned shape {values.shape}, expected ({len(texels)}, 3)"
            )
        return values


class _Tracer:
    """The Embree scene of a mesh, with what shading needs per triangle and vertex."""

    def __init__(self, scene: Scene, epsilon: float | None):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        mesh = scene.mesh
        self.scene = scene
        self.embree = rtcore_scene.EmbreeScene()
        # Keep the geometry object alive as long as the Embree scene.
        self._geometry = TriangleMesh(self.embree, mesh.vertices, mesh.triangles)
        self.vertices = mesh.vertices.astype(np.float64)
        self.face_normals = mesh.face_normals()
        if epsilon is None:
            epsilon = 1e-4 * float(np.linalg.norm(np.ptp(self.vertices, axis=0)))
        self.epsilon = epsilon

    def intersect(self, origins: np.ndarray, directions: np.ndarray):
        hits = self.embree.run(_f32(origins), _f32(directions), output=1)
        return hits["primID"], hits["u"], hits["v"]

    def unoccluded(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray
    ) -> np.ndarray:
        dists = np.full(len(origins), tfar, dtype=np.float32)
        return self.embree.run(_f32(origins), _f32(directions), dists=dists, query="OCCLUDED") == -1


def _f32(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _shade(
    tracer: _Tracer,
    material: _CountingMaterial,
    x: np.ndarray,
    y: np.ndarray,
    background: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Radiance (n, 3) of the camera rays through pixel points (x, y), the indices of the
    rays that hit cloth lit by some light, and the number of shadow rays traced."""
    scene, mesh = tracer.scene, tracer.scene.mesh
    origins, directions = scene.camera.rays(x, y)
    prim, bary_u, bary_v = tracer.intersect(origins, directions)
    radiance = np.tile(background, (len(x), 1))
    hit = np.flatnonzero(prim >= 0)
    radiance[hit] = 0.0
    triangle = prim[hit]
    bary = np.column_stack([1.0 - bary_u[hit] - bary_v[hit], bary_u[hit], bary_v[hit]])
    corners = mesh.triangles[triangle]

    def interpolate(per_vertex: np.ndarray) -> np.ndarray:
        return np.einsum("kj,kjd->kd", bary, per_vertex[corners])

    position = interpolate(tracer.vertices)
    normal = normalized(interpolate(mesh.normals))
    tangent = interpolate(mesh.tangents)
    tangent = normalized(tangent - _dot(tangent, normal)[:, None] * normal)
    bitangent = np.cross(normal, tangent)
    geometric = tracer.face_normals[triangle]
    view = -directions[hit]
    front = (_dot(view, normal) > 0) & (_dot(view, geometric) > 0)
    shadow_origin = position + tracer.epsilon * geometric

    # Lit (hit, light) pairs, light by light: which hit, direction to the light, E_perp.
    lit_hits, lit_dirs, lit_irradiance = [], [], []
    shadow_rays = 0
    for light in scene.lights:
        if isinstance(light, PointLight):
            to_light = light.position - position
            distance2 = _dot(to_light, to_light)
            to_light = to_light / np.sqrt(distance2)[:, None]
            irradiance = light.intensity / distance2[:, None]
            shadow_dirs, tfar = light.position - shadow_origin, _SHADOW_STOP
        else:
            to_light = np.broadcast_to(light.direction, position.shape)
            irradiance = np.broadcast_to(light.irradiance, position.shape)
            shadow_dirs, tfar = to_light, np.inf
        ok = np.flatnonzero(front & (_dot(to_light, normal) > 0) & (_dot(to_light, geometric) > 0))
        visible = tracer.unoccluded(shadow_origin[ok], shadow_dirs[ok], tfar)
        shadow_rays += len(ok)
        ok = ok[visible]
        lit_hits.append(ok)
        lit_dirs.append(to_light[ok])
        lit_irradiance.append(irradiance[ok])
    pair_hit = np.concatenate(lit_hits)
    light_dir = np.concatenate(lit_dirs)
    frame = np.stack([tangent[pair_hit], bitangent[pair_hit], normal[pair_hit]], axis=1)
    theta_l, phi_l = spherical(np.einsum("kij,kj->ki", frame, light_dir))
    theta_v, phi_v = spherical(np.einsum("kij,kj->ki", frame, view[pair_hit]))

    value = np.zeros((len(pair_hit), 3), dtype=np.float64)
    material_id = mesh.material_ids[triangle[pair_hit]]
    cloth = np.flatnonzero(material_id == CLOTH)
    if len(cloth):
        texels = texels_of_uv(interpolate(mesh.uv)[pair_hit[cloth]], material.crop_size)
        directions4 = np.column_stack([theta_l[cloth], phi_l[cloth], theta_v[cloth], phi_v[cloth]])
        value[cloth] = material.evaluate(texels, directions4)
    floor = np.flatnonzero(material_id == FLOOR)
    value[floor] = scene.floor_albedo / np.pi * np.cos(theta_l[floor])[:, None]
    contribution = np.maximum(value, 0.0) * np.concatenate(lit_irradiance)
    np.add.at(radiance, hit[pair_hit], contribution)  # in light order, as the pairs are
    on_lit_cloth = np.unique(hit[pair_hit[cloth]])
    return radiance, on_lit_cloth, shadow_rays
