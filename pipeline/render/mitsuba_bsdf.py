"""Any :class:`~pipeline.render.materials.Material` as a Mitsuba 3 BSDF plugin.

:func:`register` registers the BSDF ``pipeline_btf`` (:data:`PLUGIN`) with Mitsuba for a
variant, choosing one when none is given (:func:`choose_variant`); importing the module
changes no Mitsuba state. After ``register()`` a scene file naming it loads::

    <bsdf type="pipeline_btf">
        <string name="loader" value="package.module:function"/>  <!-- function(path) -> Material -->
        <string name="filename" value="btf.safetensors"/>       <!-- resolved like a mesh file -->
    </bsdf>

A material object already in memory is bound with :func:`material_bsdf` (an instance to put
in ``mi.load_dict``). After changing the variant, call :func:`register` again.

Conventions: those of :mod:`pipeline.render.engine`, with these Mitsuba specifics.

Tangent frame
    Mitsuba's shading frame has n = the interpolated vertex normal and s = dP/du of the
    *triangle* (from its uv), made orthogonal to n; t = n x s. The project's renderer's
    interpolated vertex tangent differs from s by a rotation about n (on the folded sheet
    up to 10 degrees at 96 quads per side, 27 at 24). So where the shape carries the
    vertex attribute ``vertex_tangent`` (PLY properties ``tangent_x, tangent_y,
    tangent_z``, as :mod:`pipeline.btf.render.mitsuba_scene` writes), the tangent is that
    attribute, as in the project's renderer; elsewhere it is Mitsuba's s.
Directions
    In radiance transport (Mitsuba's default, every camera integrator) the light is ``wo``
    and the view ``si.wi``.
uv to texel
    Mitsuba 3.9 keeps a PLY file's v as written (``flip_tex_coords`` defaults to false for
    PLY) but flips an OBJ file's (v -> 1 - v, ``flip_tex_coords`` true): write PLY, or
    OBJ with ``flip_tex_coords`` false.
Cosine
    A material value already holds the cosine foreshortening of the light, and Mitsuba's
    ``BSDF.eval`` returns "the BSDF f(wi, wo) ... multiplied by the cosine foreshortening
    term" (its docstring) cos theta_o: the value is returned as it is, divided by nothing.
    In importance transport (adjoint, ``TransportMode.Importance``) the light is ``wi``,
    so the value is multiplied by cos theta_o / cos theta_i.
Visibility and sign
    As in the project's renderer, with the geometric normal ``si.n``.
Sampling
    Cosine-weighted hemisphere about the shading normal, pdf ``cos theta_o / pi`` (zero
    for a view below the surface); ``sample`` returns ``eval / pdf`` as its weight.
Batches
    ``eval`` converts Mitsuba's arrays to numpy and asks the material once per call: in
    the ``llvm_*`` variants, with Dr.Jit's symbolic calls off
    (``dr.JitFlag.SymbolicCalls``; :func:`evaluated_calls`), one call holds every lane of
    the wavefront that reaches this BSDF; in ``scalar_rgb`` it holds one sample. Under a
    symbolic call the arrays hold no values and ``eval`` raises a RuntimeError saying so.

Examples
--------
>>> import mitsuba as mi  # doctest: +SKIP
>>> from pipeline.render.materials import LambertianTexture  # doctest: +SKIP
>>> bsdf = material_bsdf(LambertianTexture(np.full((2, 2, 3), 0.5)))  # doctest: +SKIP
>>> mi.load_dict({"type": "sphere", "bsdf": bsdf})  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Iterator

import numpy as np

from pipeline.render.materials import check_crop_size, spherical, texels_of_uv

try:
    import drjit as dr
    import mitsuba as mi
except ImportError:  # the plugin is optional: the rest of the renderer works without it
    dr = mi = None

PLUGIN = "pipeline_btf"
TANGENT_ATTRIBUTE = "vertex_tangent"
DEFAULT_VARIANT = "scalar_rgb"
LLVM_VARIANT = "llvm_ad_rgb"
# Mitsuba 3.9.1's kernels abort the process on LLVM 15 ("LLVM ERROR: Cannot select: ...
# fminimum"); LLVM 19 (Debian's libllvm19) works. Versions between were not tried.
MIN_LLVM = (19, 0, 0)
INSTALL_HINT = "install Mitsuba 3 (pip install mitsuba==3.9.1)"

_CLASSES: dict[str, type] = {}  # variant -> the BSDF class defined for it


def _require_mitsuba() -> None:
    if mi is None:
        raise ImportError(f"the pipeline_btf BSDF needs Mitsuba 3: {INSTALL_HINT}")


def llvm_version() -> tuple[int, int, int] | None:
    """The version of the LLVM library that Dr.Jit loads (``DRJIT_LIBLLVM_PATH`` or its
    own search), or None when it finds none. Asks through the variant
    :data:`LLVM_VARIANT`, which compiles nothing (a too-old LLVM is found out without
    running a kernel on it), then sets the variant that was set before, if any."""
    _require_mitsuba()
    if LLVM_VARIANT not in mi.variants():
        return None
    before = mi.variant()
    try:
        mi.set_variant(LLVM_VARIANT)
        version = tuple(int(v) for v in dr.detail.llvm_version())
    except (RuntimeError, ImportError, AttributeError):
        version = None
    finally:
        if before is not None:
            mi.set_variant(before)
    return version if version and version > (0, 0, 0) else None


def choose_variant() -> str:
    """:data:`LLVM_VARIANT` when Dr.Jit loads an LLVM of at least :data:`MIN_LLVM`, else
    :data:`DEFAULT_VARIANT` (one sample per BSDF call: slow for large frames)."""
    version = llvm_version()
    return LLVM_VARIANT if version is not None and version >= MIN_LLVM else DEFAULT_VARIANT


def register(variant: str | None = None) -> str:
    """Register :data:`PLUGIN` for ``variant`` (set first), or for the current variant, or
    for :func:`choose_variant`'s when none is set; returns the variant."""
    _require_mitsuba()
    if variant is not None:
        if variant not in mi.variants():
            raise ValueError(f"variant={variant!r} is not one of {list(mi.variants())}")
        mi.set_variant(variant)
    elif mi.variant() is None:
        mi.set_variant(choose_variant())
    variant = mi.variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _define_class()
        cls = _CLASSES[variant]
        mi.register_bsdf(PLUGIN, lambda props: cls(props))
    return variant


def material_bsdf(material, tangent_attribute: str = TANGENT_ATTRIBUTE):
    """A :data:`PLUGIN` BSDF of the current variant that answers with ``material`` (an
    object with ``crop_size`` and ``evaluate(texels, directions)``), for ``mi.load_dict``."""
    register()
    props = mi.Properties(PLUGIN)
    props["tangent_attribute"] = tangent_attribute
    return _CLASSES[mi.variant()](props, material=material)


@contextlib.contextmanager
def evaluated_calls() -> Iterator[None]:
    """Dr.Jit's calls and loops evaluated (wavefront) rather than recorded, while inside:
    a render of a scene holding :data:`PLUGIN` needs it in the ``llvm_*`` variants."""
    _require_mitsuba()
    with (
        dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False),
        dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False),
    ):
        yield


def load_material(loader: str, path: str):
    """``function(path)`` for ``loader`` = ``"package.module:function"``: the material of
    a scene file's BSDF. Raises ValueError naming a loader that is not importable."""
    module_name, colon, name = str(loader).partition(":")
    if not (colon and module_name and name):
        raise ValueError(f"loader={loader!r} must be 'package.module:function'")
    try:
        function = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as error:
        raise ValueError(f"loader={loader!r} cannot be imported: {error}") from None
    return function(path)


def btf_query(material, uv, wi, wo, geometric, tangent_angle=None, importance=False):
    """The BSDF value of ``material`` at shading points given as numpy arrays, all in
    Mitsuba's shading frame (s, t, n).

    Parameters
    ----------
    material : a Material (``crop_size``, ``evaluate``).
    uv : ndarray of shape (n, 2)
    wi, wo : ndarray of shape (n, 3), unit: towards the view and towards the light
        (radiance transport), or the reverse (``importance``).
    geometric : ndarray of shape (n, 3), the geometric normal.
    tangent_angle : ndarray of shape (n,) or None
        The angle from s towards t of the project's tangent (the vertex tangent projected
        onto the tangent plane): its frame is Mitsuba's turned by it about n, so its phi
        is Mitsuba's less it. None: no turn.

    Returns
    -------
    ndarray of shape (n, 3), float32: the material's value, zero where a direction is
    below the shading or geometric normal, clamped at 0.
    """
    valid = (
        (wi[:, 2] > 0)
        & (wo[:, 2] > 0)
        & (np.einsum("ij,ij->i", wi, geometric) > 0)
        & (np.einsum("ij,ij->i", wo, geometric) > 0)
    )
    out = np.zeros((len(uv), 3), dtype=np.float32)
    index = np.flatnonzero(valid)
    if len(index) == 0:
        return out
    view, light = wi[index], wo[index]
    if importance:
        view, light = light, view
    theta_l, phi_l = spherical(light)
    theta_v, phi_v = spherical(view)
    if tangent_angle is not None:
        turn = tangent_angle[index]
        phi_l, phi_v = np.mod(phi_l - turn, 2.0 * np.pi), np.mod(phi_v - turn, 2.0 * np.pi)
    directions = np.column_stack([theta_l, phi_l, theta_v, phi_v])
    value = np.asarray(
        material.evaluate(texels_of_uv(uv[index], material.crop_size), directions), dtype=np.float32
    )
    value = np.maximum(value, 0.0)
    if importance:  # the cosine belongs to wo (the view here), not to the light
        value *= (wo[index, 2] / wi[index, 2]).astype(np.float32)[:, None]
    out[index] = value
    return out


def _columns(value, width: int) -> np.ndarray:
    """A Mitsuba vector or point (scalar or one lane per sample) as ndarray (n, width)."""
    return np.asarray(value, dtype=np.float64).reshape(width, -1).T


def _define_class() -> type:
    """The BSDF class for the current variant (``mi.BSDF`` is the variant's own class)."""
    flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.SpatiallyVarying

    class MaterialBSDF(mi.BSDF):
        """A Material as a BSDF (module docstring); ``material`` from ``props``'
        ``loader`` and ``filename`` unless given."""

        def __init__(self, props, material=None):
            mi.BSDF.__init__(self, props)
            self.tangent_attribute = str(props.get("tangent_attribute", TANGENT_ATTRIBUTE))
            if material is None:
                for key in ("loader", "filename"):
                    if key not in props:
                        raise ValueError(f"the {PLUGIN} BSDF needs a string '{key}'")
                path = mi.file_resolver().resolve(str(props["filename"]))
                material = load_material(str(props["loader"]), str(path))
            if not callable(getattr(material, "evaluate", None)):
                raise ValueError(f"{material!r} has no evaluate(texels, directions) method")
            check_crop_size(material.crop_size)
            self.material = material
            self.m_components = [flags]
            self.m_flags = flags

        def _value(self, ctx, si, wo, active):
            if dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(
                    f"the {PLUGIN} BSDF evaluates numpy arrays and cannot be recorded: "
                    "render inside pipeline.render.mitsuba_bsdf.evaluated_calls() (Dr.Jit's "
                    "SymbolicCalls and SymbolicLoops flags off)"
                )
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
                return mi.Color3f(0.0)
            wi, wo_ = _columns(si.wi, 3), _columns(wo, 3)
            n = len(wi)
            index = np.flatnonzero(
                np.broadcast_to(np.asarray(active, dtype=bool).reshape(-1), (n,))
            )
            tangent_angle = None
            shape = si.shape
            if shape is not None:
                has = shape.has_attribute(self.tangent_attribute, active)
                if np.any(has):
                    tangent = si.to_local(
                        mi.Vector3f(
                            shape.eval_attribute_3(self.tangent_attribute, si, active & has)
                        )
                    )
                    along_s, along_t = _columns(tangent.x, 1)[:, 0], _columns(tangent.y, 1)[:, 0]
                    # Where there is none (zeros) or it is along n, the angle is 0.
                    tangent_angle = np.arctan2(along_t, along_s)[index]
            out = np.zeros((n, 3), dtype=np.float32)
            out[index] = btf_query(
                self.material,
                _columns(si.uv, 2)[index],
                wi[index],
                wo_[index],
                _columns(si.to_local(si.n), 3)[index],
                tangent_angle,
                ctx.mode == mi.TransportMode.Importance,
            )
            if not dr.is_jit_v(mi.Float):  # one sample
                return mi.Color3f(*(float(v) for v in out[0]))
            return mi.Color3f(out.T)

        def eval(self, ctx, si, wo, active=True):
            return self._value(ctx, si, wo, active)

        def pdf(self, ctx, si, wo, active=True):
            cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
            ok = (cos_i > 0) & (cos_o > 0) & ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)
            return dr.select(ok & active, cos_o * dr.inv_pi, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self._value(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = self.pdf(ctx, si, wo, active)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            value = self._value(ctx, si, wo, active & (bs.pdf > 0))
            return bs, dr.select(bs.pdf > 0, value / dr.maximum(bs.pdf, 1e-30), 0.0)

        def traverse(self, callback):
            pass  # nothing differentiable: the material is numpy

        def to_string(self):
            rows, cols = self.material.crop_size
            return (
                f"MaterialBSDF[material={type(self.material).__name__}, "
                f"crop_size=({rows}, {cols}), tangent_attribute={self.tangent_attribute!r}]"
            )

    return MaterialBSDF
