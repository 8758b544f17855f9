"""The fabrics :class:`pipeline.btf.synthetic.SyntheticBTF` renders: one preset each.

A preset is a frozen dataclass that holds all of its material's constants and builds its
texture in two methods: :meth:`Material.surface` (which yarn is visible per texel, the
height field, the in-plane fibre direction, the thread each texel belongs to) and
:meth:`Material.albedo` (the diffuse colour per texel). The renderer turns these into
normals, twisted tangents, a depth for self-shadowing and an Ashikhmin–Shirley lobe,
the same way for every preset. The look of each visible yarn (its label) is a
:class:`Yarn`; a preset's ``yarns`` are indexed by label. The presets (:data:`MATERIALS`):
``plain_weave`` (:class:`PlainWeave`), ``knit`` (:class:`Knit`), ``corduroy``
(:class:`Corduroy`) and ``satin`` (:class:`Satin`).

Coordinates: x along image columns (to the right), y along image rows (downward); a
fibre direction ``(cos α, sin α)`` has azimuth α from +x toward +y, as φ does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from pipeline.core.errors import ConfigError

WARP, WEFT, GAP = 0, 1, 2  # labels of plain_weave and satin


@dataclass(frozen=True)
class Yarn:
    """The look of the texels of one label.

    ``shadow`` weights the isotropic self-shadowing ``tan θ · depth``; ``shadow_across``
    weights ``tan θ · depth · |sin(φ - α)|``, the shadow the walls of the yarn's channel
    cast on light that crosses the fibre (azimuth α) rather than runs along it; both
    are scaled by the preset's ``shadow_strength``.
    Exponents are Ashikhmin–Shirley's along the fibre tangent and across it.
    """

    name: str
    albedo: tuple[float, float, float]  # linear RGB, before per-thread variation
    specular: float
    exponent_along: float
    exponent_across: float
    twist_degrees: float = 0.0  # tangent turned about the normal (S-twist positive)
    shadow: float = 0.35
    shadow_across: float = 0.0


@dataclass(frozen=True)
class Surface:
    """What a preset's geometry gives the renderer; S = texture size.

    Attributes
    ----------
    labels : ndarray of shape (S, S), int, index into the preset's ``yarns``
    height : ndarray of shape (S, S), float64, in texels (finite differences are slopes), smooth
    fibre : ndarray of shape (S, S, 2), float64, unit in-plane direction (x, y) of the fibre
    thread : ndarray of shape (S, S), int
        The thread (wale, course) a texel belongs to, for per-thread colour variation.
    """

    labels: np.ndarray
    height: np.ndarray
    fibre: np.ndarray
    thread: np.ndarray


@dataclass(frozen=True, kw_only=True)
class Material:
    """What every preset declares; subclasses add their geometry constants and methods."""

    yarns: tuple[Yarn, ...]
    n_threads: int  # default repeats across the texture (threads or wales)
    exposure: float  # chosen so that few values clip at 1 (shares per preset: docs/results.md)
    shadow_strength: float
    fresnel_at_normal: float = 0.05

    @property
    def label_names(self) -> tuple[str, ...]:
        return tuple(yarn.name for yarn in self.yarns)

    def check_threads(self, n_threads: int) -> None:
        """Raise ConfigError unless ``n_threads`` repeats tile the texture."""
        if not isinstance(n_threads, int | np.integer) or n_threads < 1:
            raise ConfigError(f"n_threads={n_threads!r} must be an integer >= 1")

    def surface(self, size: int, n_threads: int, rng: np.random.Generator) -> Surface:
        """The texture's geometry, ``n_threads`` repeats across ``size`` texels."""
        raise NotImplementedError

    def albedo(self, surface: Surface, n_threads: int, rng: np.random.Generator) -> np.ndarray:
        """Diffuse albedo, ndarray of shape (S, S, 3), float64 (clipped by the caller)."""
        raise NotImplementedError


# --- helpers shared by the presets -------------------------------------------------------


def texel_grid(size: int, periods: float) -> tuple[np.ndarray, np.ndarray]:
    """(y, x) texel centres in repeat units, each ndarray of shape (size, size)."""
    centres = (np.arange(size) + 0.5) * periods / size
    return np.meshgrid(centres, centres, indexing="ij")


def height_to_texels(height: np.ndarray, size: int, periods: float, blur: float) -> np.ndarray:
    """Heights in repeat units to texels, lightly blurred to soften vertical cliffs."""
    return gaussian_filter(height * size / periods, sigma=blur, mode="wrap")


def fibre_noise(rng: np.random.Generator, shape, sigma, amount: float) -> np.ndarray:
    """Multiplicative noise ``1 + amount · n`` with n blurred, unit-variance, tiling."""
    noise = gaussian_filter(rng.normal(0.0, 1.0, size=shape), sigma, mode="wrap")
    return 1.0 + amount * noise / max(noise.std(), 1e-12)


def thread_variation(rng, n_families: int, n_threads: int, spread: float, tint: float):
    """Per-thread colour factors, ndarray (n_families, n_threads, 3): a gain in
    ``1 ± spread`` times a hue shift of standard deviation ``tint``."""
    gain = rng.uniform(1.0 - spread, 1.0 + spread, size=(n_families, n_threads, 1))
    return gain * (1.0 + rng.normal(0.0, tint, size=(n_families, n_threads, 3)))


def yarn_colours(yarns: tuple[Yarn, ...], labels: np.ndarray) -> np.ndarray:
    return np.array([yarn.albedo for yarn in yarns])[labels]


def axis_fibre(along_y: np.ndarray) -> np.ndarray:
    """(S, S, 2) fibre directions: +y where ``along_y``, +x elsewhere."""
    return np.stack([~along_y, along_y], axis=-1).astype(np.float64)


def smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def round_thread(centre_line, across, half_width, radius):
    """Height of a thread with an elliptic cross-section; -inf outside it."""
    inside = np.abs(across) < half_width
    bulge = np.sqrt(np.clip(1.0 - (across / half_width) ** 2, 0.0, None))
    return np.where(inside, centre_line + radius * bulge, -np.inf)


# --- the presets ------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Woven(Material):
    """A weave of round threads, warp along +y and weft along +x (plain_weave, satin)."""

    thread_half_width: float  # in thread periods; the rest of the period is gap
    thread_radius: float  # crest height above the thread's centre line, in periods
    undulation: float  # how far a thread dips under its crossing threads

    def woven_surfaces(self, x, y, warp_centre, weft_centre) -> np.ndarray:
        """Heights of the warp, the weft and the floor, stacked (3, S, S): the top one is
        what a texel shows. Threads sit at whole periods of x (warp) and y (weft), their
        centre lines at ``warp_centre`` and ``weft_centre``."""
        half_width, radius = self.thread_half_width, self.thread_radius
        return np.stack([
            round_thread(warp_centre, x - np.floor(x) - 0.5, half_width, radius),
            round_thread(weft_centre, y - np.floor(y) - 0.5, half_width, radius),
            np.full_like(x, -self.undulation - radius),
        ])  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class PlainWeave(Woven):
    """Plain weave: madder-red warp along +y and beige weft along +x, warp k on top where
    k + row of crossing is even; glossy twisted yarn, dark gaps. Labels: 0 warp, 1 weft,
    2 gap."""

    yarns: tuple[Yarn, ...] = (
        Yarn("warp", albedo=(0.55, 0.10, 0.08), specular=0.45, exponent_along=90.0,
             exponent_across=6.0, twist_degrees=25.0, shadow_across=0.65),  # madder red, S-twist
        Yarn("weft", albedo=(0.70, 0.62, 0.42), specular=0.30, exponent_along=40.0,
             exponent_across=3.0, twist_degrees=-15.0, shadow_across=0.65),  # undyed beige, Z
        Yarn("gap", albedo=(0.05, 0.04, 0.035), specular=0.05, exponent_along=5.0,
             exponent_across=5.0, shadow=1.0),  # the dark floor between threads
    )  # fmt: skip
    n_threads: int = 4
    exposure: float = 3.0
    shadow_strength: float = 0.55
    thread_half_width: float = 0.4
    thread_radius: float = 0.3
    undulation: float = 0.15

    def check_threads(self, n_threads):
        if not isinstance(n_threads, int | np.integer) or n_threads < 2 or n_threads % 2:
            raise ConfigError(
                f"n_threads={n_threads!r} must be an even integer >= 2 for plain_weave"
            )

    def surface(self, size, n_threads, rng):
        y, x = texel_grid(size, n_threads)
        warp_index, weft_index = np.floor(x), np.floor(y)
        warp_centre = self.undulation * np.cos(np.pi * (y - 0.5) + np.pi * warp_index)
        weft_centre = -self.undulation * np.cos(np.pi * (x - 0.5) + np.pi * weft_index)
        surfaces = self.woven_surfaces(x, y, warp_centre, weft_centre)
        labels = np.argmax(surfaces, axis=0)
        return Surface(
            labels=labels,
            height=height_to_texels(np.max(surfaces, axis=0), size, n_threads, blur=0.7),
            fibre=axis_fibre(labels == WARP),
            thread=np.where(labels == WARP, warp_index, weft_index).astype(np.int64),
        )

    def albedo(self, surface, n_threads, rng):
        variation = thread_variation(rng, 2, n_threads, spread=0.2, tint=0.04)
        labels = surface.labels
        albedo = yarn_colours(self.yarns, labels)
        for yarn in (WARP, WEFT):
            on_yarn = labels == yarn
            albedo[on_yarn] *= variation[yarn][surface.thread[on_yarn]]
        return albedo * fibre_noise(rng, labels.shape, 0.6, 0.12)[..., None]


@dataclass(frozen=True, kw_only=True)
class Knit(Material):
    """Jersey knit, face side: columns (wales) of V-shaped loops, each V two rounded legs
    at ±60° from the rows that meet at the bottom, nested into the V below; fuzzy heathered
    blue-grey wool with a broad, weak sheen, deep gaps between the loops. Labels: 0 left
    leg (fibre at 60°), 1 right leg (120°), 2 gap."""

    yarns: tuple[Yarn, ...] = (
        Yarn("left leg", albedo=(0.36, 0.44, 0.56), specular=0.06, exponent_along=8.0,
             exponent_across=3.0, twist_degrees=10.0, shadow=0.5, shadow_across=0.9),
        Yarn("right leg", albedo=(0.36, 0.44, 0.56), specular=0.06, exponent_along=8.0,
             exponent_across=3.0, twist_degrees=10.0, shadow=0.5, shadow_across=0.9),
        Yarn("gap", albedo=(0.04, 0.04, 0.05), specular=0.02, exponent_along=3.0,
             exponent_across=3.0, shadow=1.2),
    )  # fmt: skip
    heather: tuple[float, float, float] = (0.62, 0.62, 0.66)  # undyed fibres in the blend
    n_threads: int = 4  # wales across the texture
    exposure: float = 3.0
    shadow_strength: float = 0.6
    course_height: float = 0.6  # course spacing in wale widths (rounded so courses tile)
    leg_angle: float = 60.0  # degrees between a leg and the rows
    leg_length: float = 0.48  # semi-axis along the leg, in wale widths
    leg_width: float = 0.2  # semi-axis across the leg
    leg_radius: float = 0.3  # crest height of a leg above its ends
    leg_rise: float = 0.1  # how much higher a leg's bottom end lies (it passes over the
    # head of the loop below) than its top (which dives under the loop above)
    floor: float = -0.12  # gap floor height
    groove: float = 0.15  # depth of the crease where two legs meet
    groove_width: float = 0.1  # height difference over which the crease fades
    fuzz: float = 0.01  # height noise of the hairy wool, in wale widths
    blur: float = 0.6  # in texels
    cavity: float = 0.7  # albedo darkening toward the gaps (light that gets in stays there)

    def course_count(self, n_threads: int) -> int:
        """Courses (rows of loops) down the texture: a whole number, so they tile."""
        return max(1, round(n_threads / self.course_height))

    def surface(self, size, n_threads, rng):
        n_courses = self.course_count(n_threads)
        course = n_threads / n_courses
        y, x = texel_grid(size, n_threads)
        wale, row = np.floor(x), np.floor(y / course)
        cos_a, sin_a = np.cos(np.deg2rad(self.leg_angle)), np.sin(np.deg2rad(self.leg_angle))
        offset = self.leg_length * cos_a  # a V's legs meet on the wale's centre line
        heights, labels, courses = [], [], []
        for side, label in ((-1, 0), (1, 1)):  # left leg runs at +60°, the right at 120°
            ux, uy = -side * cos_a, sin_a  # along the leg, downward
            for dk in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    dx = x - (wale + dk + 0.5 + side * offset)
                    dy = y - (row + dj + 0.5) * course
                    along = (dx * ux + dy * uy) / self.leg_length
                    across = (dy * ux - dx * uy) / self.leg_width
                    inside = along**2 + across**2 < 1
                    bulge = np.sqrt(np.clip(1 - along**2 - across**2, 0, None))
                    heights.append(np.where(
                        inside, self.leg_radius * bulge + self.leg_rise * along, -np.inf
                    ))  # fmt: skip
                    labels.append(label)
                    courses.append(np.mod(row + dj, n_courses))
        heights.append(np.full_like(x, self.floor))
        labels.append(GAP)
        courses.append(np.zeros_like(x))
        heights = np.stack(heights)
        top = np.argmax(heights, axis=0)
        label = np.array(labels)[top]
        # Where two legs meet, press a groove in: each leg reads as its own rounded grain.
        second, height = np.partition(heights, -2, axis=0)[-2:]
        height = height - self.groove * np.exp(-(height - second) / self.groove_width)
        height += self.fuzz * (fibre_noise(rng, x.shape, 0.8, 1.0) - 1.0)
        leg_direction = np.array([[cos_a, sin_a], [-cos_a, sin_a], [1.0, 0.0]])
        return Surface(
            labels=label,
            height=height_to_texels(height, size, n_threads, blur=self.blur),
            fibre=leg_direction[label],
            thread=np.take_along_axis(np.stack(courses), top[None], 0)[0].astype(np.int64),
        )

    def albedo(self, surface, n_threads, rng):
        labels = surface.labels
        n_courses = self.course_count(n_threads)  # the yarn runs along a course
        variation = thread_variation(rng, 1, n_courses, spread=0.06, tint=0.03)[0]
        # Heather: dyed and undyed fibres mixed, in blotches a few fibres wide.
        mix = smoothstep(1.3, 1.9, fibre_noise(rng, labels.shape, 0.9, 0.5))[..., None]
        albedo = yarn_colours(self.yarns, labels) * (1 - mix) + np.array(self.heather) * mix
        on_yarn = labels != GAP
        albedo[on_yarn] *= variation[surface.thread[on_yarn]]
        albedo[~on_yarn] = self.yarns[GAP].albedo
        depth = (surface.height.max() - surface.height) / max(np.ptp(surface.height), 1e-12)
        albedo *= (1 - self.cavity * depth)[..., None]
        return albedo * fibre_noise(rng, labels.shape, 0.6, 0.15)[..., None]


@dataclass(frozen=True, kw_only=True)
class Corduroy(Material):
    """Corduroy: rounded cut-pile ridges (wales) along +y with deep valleys between them;
    dark olive pile with a dull, broad sheen, a slightly different shade per wale, and
    little light reaching the ground weave. Labels: 0 crest, 1 flank, 2 valley."""

    yarns: tuple[Yarn, ...] = (
        Yarn("crest", albedo=(0.25, 0.26, 0.11), specular=0.10, exponent_along=10.0,
             exponent_across=4.0, shadow=0.2, shadow_across=1.6),
        Yarn("flank", albedo=(0.21, 0.22, 0.09), specular=0.08, exponent_along=10.0,
             exponent_across=4.0, shadow=0.4, shadow_across=1.6),
        Yarn("valley", albedo=(0.06, 0.06, 0.03), specular=0.03, exponent_along=5.0,
             exponent_across=5.0, shadow=1.0, shadow_across=1.0),
    )  # fmt: skip
    n_threads: int = 6  # wales across the texture
    exposure: float = 3.0
    shadow_strength: float = 0.8
    ridge_half_width: float = 0.42  # in wale widths; the rest is valley
    ridge_height: float = 0.5
    ridge_roundness: float = 2.5  # superellipse exponent: 2 round, larger flatter tops
    crest: float = 0.55  # fraction of the half width counted as crest
    pile: float = 0.02  # height of the pile's streaks along the wale

    def surface(self, size, n_threads, rng):
        y, x = texel_grid(size, n_threads)
        across = np.abs(x - np.floor(x) - 0.5) / self.ridge_half_width
        profile = np.clip(1 - across**self.ridge_roundness, 0, None) ** (1 / self.ridge_roundness)
        streaks = fibre_noise(rng, x.shape, (3.0, 0.5), 1.0) - 1.0  # long along y
        height = self.ridge_height * profile + self.pile * streaks * (across < 1)
        labels = np.where(across < self.crest, 0, np.where(across < 1, 1, 2))
        return Surface(
            labels=labels,
            height=height_to_texels(height, size, n_threads, blur=0.7),
            fibre=axis_fibre(np.ones_like(labels, dtype=bool)),
            thread=np.floor(x).astype(np.int64),
        )

    def albedo(self, surface, n_threads, rng):
        variation = thread_variation(rng, 1, n_threads, spread=0.08, tint=0.05)[0]
        albedo = yarn_colours(self.yarns, surface.labels) * variation[surface.thread]
        streaks = fibre_noise(rng, surface.labels.shape, (2.5, 0.5), 0.12)
        return albedo * streaks[..., None]


@dataclass(frozen=True, kw_only=True)
class Satin(Woven):
    """Printed 5-harness satin: warp floats along +y over 4 wefts and under 1 (warp k goes
    under weft j only where j ≡ 3k (mod 5), so along a weft the binding warps step by 2);
    a narrow, bright highlight along the floats, and a floral print that ignores the
    threads. Labels: 0 warp, 1 weft (at the binding points and in the slits between
    floats), 2 gap (rare: the warp is dense)."""

    # Low-twist filament; the albedo multiplies the print.
    yarns: tuple[Yarn, ...] = (
        Yarn("warp", albedo=(1.0, 1.0, 1.0), specular=0.5, exponent_along=300.0,
             exponent_across=30.0, twist_degrees=2.0, shadow=0.3, shadow_across=0.5),
        Yarn("weft", albedo=(0.9, 0.9, 0.9), specular=0.3, exponent_along=100.0,
             exponent_across=20.0, shadow=0.3, shadow_across=0.5),
        Yarn("gap", albedo=(0.3, 0.3, 0.3), specular=0.05, exponent_along=5.0,
             exponent_across=5.0, shadow=1.0),
    )  # fmt: skip
    n_threads: int = 10  # warp (and weft) threads across; a multiple of 5
    exposure: float = 2.4  # lower: the floats' highlight is brightest at the mirror directions
    shadow_strength: float = 0.5
    thread_half_width: float = 0.47
    thread_radius: float = 0.18
    undulation: float = 0.12
    dip_width: float = 0.5  # standard deviation of a binding point's dip, in threads
    arch: float = 0.2  # how much a float bulges up between its binding points
    # The print: five-petal flowers on a half-drop lattice, small dots between them.
    motifs: int = 2  # flowers per side of the texture
    ground: tuple[float, float, float] = (0.05, 0.07, 0.24)  # navy
    petal: tuple[float, float, float] = (0.82, 0.34, 0.40)  # coral
    centre: tuple[float, float, float] = (0.88, 0.68, 0.16)  # gold
    dot: tuple[float, float, float] = (0.78, 0.76, 0.66)  # cream

    def check_threads(self, n_threads):
        if not isinstance(n_threads, int | np.integer) or n_threads < 5 or n_threads % 5:
            raise ConfigError(f"n_threads={n_threads!r} must be a multiple of 5 for satin")

    def surface(self, size, n_threads, rng):
        y, x = texel_grid(size, n_threads)
        warp_index, weft_index = np.floor(x), np.floor(y)

        def dip(offset):  # 1 at a binding point, 0 along the float; period 5 threads
            offset = np.mod(offset + 2.5, 5.0) - 2.5
            return np.exp(-0.5 * (offset / self.dip_width) ** 2)

        from_binding = y - np.mod(3 * warp_index, 5) - 0.5
        warp_centre = self.undulation * (1 - 2 * dip(from_binding))
        warp_centre += self.arch * (1 - np.cos(2 * np.pi * from_binding / 5)) / 2
        weft_centre = self.undulation * (2 * dip(x - np.mod(2 * weft_index, 5) - 0.5) - 1)
        surfaces = self.woven_surfaces(x, y, warp_centre, weft_centre)
        labels = np.argmax(surfaces, axis=0)
        return Surface(
            labels=labels,
            height=height_to_texels(np.max(surfaces, axis=0), size, n_threads, blur=0.6),
            fibre=axis_fibre(labels != WEFT),
            thread=np.where(labels == WEFT, weft_index, warp_index).astype(np.int64),
        )

    def print_pattern(self, size: int, rng: np.random.Generator) -> np.ndarray:
        """The printed colours, ndarray of shape (size, size, 3); ignores the threads."""
        m = self.motifs
        y, x = texel_grid(size, m)
        column = np.floor(x)
        y = y + 0.5 * np.mod(column, 2)  # half-drop: odd columns shifted by half a motif
        px, py = x - column - 0.5, y - np.floor(y) - 0.5
        radius, angle = np.hypot(px, py), np.arctan2(py, px)
        turn = rng.uniform(0, 2 * np.pi, size=(m, m))[
            np.mod(np.floor(y), m).astype(int), column.astype(int)
        ]
        petal_edge = 0.36 * (0.55 + 0.45 * np.abs(np.cos(2.5 * (angle + turn))))
        texel = m / size  # one texel in motif units, to soften the print's edges
        petal = smoothstep(petal_edge + texel, petal_edge - texel, radius)
        centre = smoothstep(0.08 + texel, 0.08 - texel, radius)
        corner = np.hypot(0.5 - np.abs(px), 0.5 - np.abs(py))
        dot = smoothstep(0.07 + texel, 0.07 - texel, corner)
        colour = np.broadcast_to(np.array(self.ground), x.shape + (3,))
        for layer, weight in ((self.dot, dot), (self.petal, petal), (self.centre, centre)):
            colour = colour + (np.array(layer) - colour) * weight[..., None]
        return colour

    def albedo(self, surface, n_threads, rng):
        labels = surface.labels
        variation = thread_variation(rng, 2, n_threads, spread=0.03, tint=0.01)
        albedo = yarn_colours(self.yarns, labels) * self.print_pattern(labels.shape[0], rng)
        for yarn in (WARP, WEFT):
            on_yarn = labels == yarn
            albedo[on_yarn] *= variation[yarn][surface.thread[on_yarn]]
        return albedo * fibre_noise(rng, labels.shape, 0.6, 0.03)[..., None]


MATERIALS: dict[str, Material] = {
    "plain_weave": PlainWeave(),
    "knit": Knit(),
    "corduroy": Corduroy(),
    "satin": Satin(),
}


def get_material(name: str) -> Material:
    """The preset called ``name``; ConfigError naming the known ones otherwise."""
    if name not in MATERIALS:
        raise ConfigError(f"material={name!r} is not one of {sorted(MATERIALS)}")
    return MATERIALS[name]
