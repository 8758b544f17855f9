"""``python -m pipeline.btf.render.mitsuba_scene file=PATH/btf.safetensors out=FOLDER``: your
compressed material in a Mitsuba 3 scene.

Writes FOLDER with the Fig. 8 set-up of :func:`pipeline.render.scene.default_scene` (the
folded sheet, the floor, the point light, the camera) as Mitsuba 3 reads it::

    FOLDER/scene.xml        the scene: camera, light, integrator, the two shapes below
    FOLDER/cloth.ply        the sheet (or a sphere): positions, normals, uv, tangents
    FOLDER/floor.ply        the Lambertian floor (without floor=false)
    FOLDER/btf.safetensors  a copy of the model, read by the BSDF ``pipeline_btf``

The cloth's BSDF is :mod:`pipeline.render.mitsuba_bsdf`'s ``pipeline_btf``, which loads the
copied file with :func:`material_from_file`; its ``register()`` makes it known::

    import mitsuba as mi, pipeline.render.mitsuba_bsdf as btf_bsdf
    btf_bsdf.register()
    with btf_bsdf.evaluated_calls():
        image = mi.render(mi.load_file("FOLDER/scene.xml"))  # linear RGB

or :func:`render`, which does the same and returns numpy. ``render=true`` also renders it
into ``FOLDER/image.exr`` (linear) and ``image.png`` (gamma 2.2); ``bench=true`` renders it
with Mitsuba and with the project's renderer (:func:`pipeline.render.engine.render`) and
prints the seconds of each frame.

What matches the project's renderer, so that both render the same image up to noise
(``tests/test_mitsuba.py`` checks it): the mesh as it is (PLY keeps uv as written; the
vertex tangents, which the BSDF uses for its frame, go in as ``vertex_tangent``); the
camera's position, look-at, up and vertical field of view; a point light of the same
radiant intensity (W/sr, as :class:`~pipeline.render.scene.PointLight`); a ``diffuse``
floor of the same albedo; the ``direct`` integrator (direct light only, hard shadows) with
one light sample and no BSDF sample (a BSDF sample cannot reach a point light); a box
pixel filter (a sample counts in the pixel it falls in). Both return linear radiance;
only the PNG gets exposure and sRGB.

Settings are ``key=value`` (:data:`KEYS`; ``--help`` lists them), read before Mitsuba and
torch are imported.
"""

from __future__ import annotations

import os
import shutil
import time
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import cli
from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, OneOf
from pipeline.render.materials import Material, check_crop_size
from pipeline.render.scene import CLOTH, FLOOR, Mesh, Scene, default_scene, merge_meshes, quad

PROG = "python -m pipeline.btf.render.mitsuba_scene"
SHAPES = ("sheet", "sphere")
SCENE_FILE = "scene.xml"
MODEL_FILE = "btf.safetensors"
LOADER = "pipeline.btf.render.mitsuba_scene:material_from_file"
# The PLY vertex properties; tangent_{x,y,z} become Mitsuba's attribute "vertex_tangent".
PLY_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "u", "v", "tangent_x", "tangent_y", "tangent_z")


@dataclass(frozen=True)
class MitsubaSceneSettings:
    """The command's settings; :data:`KEYS` describes each."""

    file: str | None = None
    out: str | None = None
    spp: int = 64
    width: int = 256
    height: int = 256
    shape: str = "sheet"
    floor: bool = True
    variant: str | None = None
    render: bool = False
    bench: bool = False


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "file": ("file", cli.Text(), "the compressed model, a btf.safetensors file (required)"),
    "out": ("out", cli.Text(), "the folder to write the scene into (required)"),
    "spp": ("spp", Integer(1), "samples per pixel of the scene's sampler"),
    "width": ("width", Integer(1), "image width, pixels"),
    "height": ("height", Integer(1), "image height, pixels"),
    "shape": (
        "shape",
        OneOf(*SHAPES),
        "what the material covers: the folded sheet of Fig. 8 or a sphere",
    ),
    "floor": ("floor", OneOf(True, False), "a Lambertian floor under the shape"),
    "variant": (
        "variant",
        cli.Text(optional=True),
        "Mitsuba variant for render/bench (null: llvm_ad_rgb with LLVM >= 19, else scalar_rgb)",
    ),
    "render": ("render", OneOf(True, False), "also render the scene into out/image.exr and .png"),
    "bench": (
        "bench",
        OneOf(True, False),
        "render with Mitsuba and with the project's renderer and print seconds per frame of each",
    ),
}

COMMAND = cli.Command(
    PROG,
    KEYS,
    MitsubaSceneSettings,
    "Write a Mitsuba 3 scene of a compressed BTF. Settings and their defaults:",
    what="the Mitsuba scene command",
)


def parse(argv: list[str]) -> MitsubaSceneSettings:
    """The settings of ``argv``; raises :class:`ConfigError` naming a bad or missing one."""
    settings = COMMAND.parse(argv)
    for key in ("file", "out"):
        if getattr(settings, key) is None:
            raise ConfigError(f"{key}=... is required (--help describes the settings)")
    if not Path(settings.file).is_file():
        raise ConfigError(f"file={settings.file!r} is not a file")
    return settings


class QueryMaterial(Material):
    """A compressed model that answers ``query(texels (T,), directions (D, 4)) -> (T, D,
    3)`` (every texel at every direction) as a :class:`Material` (one texel per query):
    the queries are grouped by texel, one ``query`` call per texel.

    Parameters
    ----------
    compressed : anything with ``crop_size`` (rows, cols) and ``query``.
    """

    def __init__(self, compressed):
        if not callable(getattr(compressed, "query", None)):
            raise ValueError(f"{compressed!r} has no query(texels, directions) method")
        self.crop_size = check_crop_size(compressed.crop_size)
        self.compressed = compressed

    def _evaluate(self, texels, directions):
        order = np.argsort(texels, kind="stable")
        ordered = texels[order]
        starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
        out = np.empty((len(texels), 3), dtype=np.float32)
        for start, stop in zip(starts, np.r_[starts[1:], len(texels)], strict=True):
            rows = order[start:stop]
            out[rows] = np.asarray(
                self.compressed.query(ordered[start : start + 1], directions[rows])
            )[0]
        return out


def as_material(compressed) -> Material:
    """A compressed model as a Material: :class:`~pipeline.btf.render.surfaces.
    CompressedMaterial` when it answers paired queries (``query_pairs``), else
    :class:`QueryMaterial` (``query`` only)."""
    if callable(getattr(compressed, "query_pairs", None)):
        from pipeline.btf.render.surfaces import CompressedMaterial

        return CompressedMaterial(compressed)
    return QueryMaterial(compressed)


def material_from_file(path: str | os.PathLike) -> Material:
    """The material of a compressed file (:func:`pipeline.btf.compressed.load_compressed`):
    the loader the written scenes name."""
    from pipeline.btf.compressed import load_compressed

    return as_material(load_compressed(path))


def sphere_mesh(
    resolution: int = 48, tiles: float = 4.0, radius: float = 0.8, center=(0.0, -0.35, 0.0)
) -> Mesh:
    """A UV sphere of :data:`CLOTH` triangles, the crop repeating ``tiles`` (> 0) times from
    pole to pole and twice as often around; ``resolution`` rings (>= 2) from pole to pole
    and twice as many segments around, of ``radius`` (> 0) about ``center`` (3,).

    Tangents run along +u (eastwards, around +y), bitangents n x t along +v (northwards),
    normals outwards; one triangle per quad at the poles (no degenerate triangles).
    """
    if int(resolution) != resolution or resolution < 2:
        raise ValueError(f"resolution={resolution!r} must be an integer >= 2")
    for name, value in (("tiles", tiles), ("radius", radius)):
        if not value > 0:
            raise ValueError(f"{name}={value!r} must be > 0")
    rings, segments = int(resolution), 2 * int(resolution)
    theta = np.linspace(0.0, np.pi, rings + 1)[:, None]  # from the north pole (+y)
    phi = np.linspace(0.0, 2.0 * np.pi, segments + 1)[None, :]
    normals = np.stack(
        np.broadcast_arrays(
            np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)
        ),
        axis=-1,
    )
    tangents = np.stack(np.broadcast_arrays(np.cos(phi), 0.0 * theta, -np.sin(phi)), axis=-1)
    uv = np.stack(
        np.broadcast_arrays(2.0 * tiles * phi / (2.0 * np.pi), tiles * (1.0 - theta / np.pi)),
        axis=-1,
    )
    index = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a00, a01 = index[:-1, :-1], index[:-1, 1:]
    a11, a10 = index[1:, 1:], index[1:, :-1]
    # Both triangles have their normal outwards; the first is empty at the south pole
    # (a10 and a11 are the pole), the second at the north pole (a00 and a01 are).
    first = np.stack([a00, a10, a11], axis=-1)[:-1].reshape(-1, 3)
    second = np.stack([a00, a11, a01], axis=-1)[1:].reshape(-1, 3)
    triangles = np.concatenate([first, second])
    return Mesh(
        vertices=np.asarray(center) + radius * normals.reshape(-1, 3),
        triangles=triangles,
        uv=uv.reshape(-1, 2),
        normals=normals.reshape(-1, 3),
        tangents=tangents.reshape(-1, 3),
        material_ids=np.full(len(triangles), CLOTH),
    )


def fig8_scene(
    width: int = 256,
    height: int = 256,
    shape: str = "sheet",
    *,
    floor: bool = True,
    tiles: float = 4.0,
    resolution: int = 96,
) -> Scene:
    """The Fig. 8 scene (:func:`~pipeline.render.scene.default_scene`, one point light),
    or the same camera, light and floor with a sphere (``shape="sphere"``: a radius of 0.8
    where the sheet hangs, ``resolution // 2`` rings)."""
    if shape not in SHAPES:
        raise ValueError(f"shape={shape!r} must be one of {list(SHAPES)}")
    scene = default_scene(width, height, floor=floor, tiles=tiles, resolution=resolution)
    if shape == "sheet":
        return scene
    sphere = sphere_mesh(max(resolution // 2, 2), tiles)
    meshes = [sphere]
    if floor:
        y = float(sphere.vertices[:, 1].min()) - 0.15
        meshes.append(quad([-4.0, y, 4.0], [8.0, 0.0, 0.0], [0.0, 0.0, -8.0], material_id=FLOOR))
    return Scene(
        mesh=merge_meshes(*meshes),
        camera=scene.camera,
        lights=scene.lights,
        floor_albedo=scene.floor_albedo,
    )


def write_ply(path: str | os.PathLike, mesh: Mesh, triangles: np.ndarray | None = None) -> Path:
    """Write ``mesh`` (or its ``triangles``, indices into ``mesh.triangles``) as a binary
    PLY file with the vertex properties :data:`PLY_PROPERTIES` (float32) and faces."""
    path = Path(path)
    chosen = mesh.triangles if triangles is None else mesh.triangles[triangles]
    used, faces = np.unique(chosen, return_inverse=True)
    columns = np.column_stack(
        [mesh.vertices[used], mesh.normals[used], mesh.uv[used], mesh.tangents[used]]
    )
    vertex = np.empty(len(used), dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for i, name in enumerate(PLY_PROPERTIES):
        vertex[name] = columns[:, i]
    face = np.empty(len(chosen), dtype=[("count", "u1"), ("index", "<i4", (3,))])
    face["count"] = 3
    face["index"] = faces.reshape(-1, 3)
    header = "".join(
        [
            "ply\nformat binary_little_endian 1.0\n",
            f"element vertex {len(vertex)}\n",
            *(f"property float {name}\n" for name in PLY_PROPERTIES),
            f"element face {len(face)}\n",
            "property list uchar int vertex_indices\nend_header\n",
        ]
    )
    path.write_bytes(header.encode("ascii") + vertex.tobytes() + face.tobytes())
    return path


@dataclass(frozen=True)
class LookAt:
    """A camera's ``to_world``: Mitsuba's ``look_at`` transform."""

    origin: tuple
    target: tuple
    up: tuple


def scene_description(scene: Scene, folder: str | os.PathLike, bsdf, spp: int = 16) -> dict:
    """The Mitsuba scene of ``scene`` as a dict, writing its meshes into ``folder``.

    Parameters
    ----------
    scene : :class:`pipeline.render.scene.Scene`
    folder : where ``cloth.ply`` and ``floor.ply`` are written.
    bsdf : the cloth's BSDF: a dict (``{"type": "pipeline_btf", "loader": ..., "filename":
        ...}``) or a BSDF object (:func:`pipeline.render.mitsuba_bsdf.material_bsdf`).
    spp : the sampler's samples per pixel.

    Returns
    -------
    dict
        Plain values, :class:`LookAt` for the camera and absolute file names: pass it to
        :func:`mitsuba_dict` for ``mi.load_dict``, or to :func:`write_xml`.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    camera = scene.camera
    description = {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective",
            "fov": float(camera.fov_y_degrees),
            "fov_axis": "y",
            "to_world": LookAt(
                *(tuple(map(float, v)) for v in (camera.position, camera.look_at, camera.up))
            ),
            "film": {
                "type": "hdrfilm",
                "width": int(camera.width),
                "height": int(camera.height),
                "pixel_format": "rgb",
                "component_format": "float32",
                "rfilter": {"type": "box"},
            },
            "sampler": {"type": "independent", "sample_count": int(spp)},
        },
    }
    ids = scene.mesh.material_ids
    albedo = {"type": "rgb", "value": [float(v) for v in scene.floor_albedo]}
    floor = {"type": "diffuse", "reflectance": albedo}
    for name, material_id, shape_bsdf in (("cloth", CLOTH, bsdf), ("floor", FLOOR, floor)):
        if np.any(ids == material_id):
            path = write_ply(folder / f"{name}.ply", scene.mesh, np.flatnonzero(ids == material_id))
            description[name] = {
                "type": "ply",
                "filename": str(path.resolve()),
                "flip_tex_coords": False,
                "bsdf": shape_bsdf,
            }
    for i, light in enumerate(scene.lights):
        if hasattr(light, "position"):
            description[f"light_{i}"] = {
                "type": "point",
                "position": [float(v) for v in light.position],
                "intensity": {"type": "rgb", "value": [float(v) for v in light.intensity]},
            }
        else:  # Mitsuba's direction is the one the light travels in
            description[f"light_{i}"] = {
                "type": "directional",
                "direction": [float(-v) for v in light.direction],
                "irradiance": {"type": "rgb", "value": [float(v) for v in light.irradiance]},
            }
    return description


def mitsuba_dict(description: dict) -> dict:
    """``description`` for ``mi.load_dict``: each :class:`LookAt` as a transform."""
    import mitsuba as mi

    def convert(value):
        if isinstance(value, LookAt):
            return mi.ScalarTransform4f().look_at(
                origin=list(value.origin), target=list(value.target), up=list(value.up)
            )
        if isinstance(value, dict):
            return {key: convert(item) for key, item in value.items()}
        return value

    return convert(description)


# The XML element of each plugin type a description may hold.
_XML_TAGS = {
    "direct": "integrator",
    "path": "integrator",
    "perspective": "sensor",
    "hdrfilm": "film",
    "box": "rfilter",
    "independent": "sampler",
    "ply": "shape",
    "diffuse": "bsdf",
    "point": "emitter",
    "directional": "emitter",
}


def write_xml(description: dict, path: str | os.PathLike) -> Path:
    """Write a :func:`scene_description` (its BSDFs as dicts) as a Mitsuba 3 XML file;
    file names become relative to the file's folder."""
    from pipeline.render.mitsuba_bsdf import PLUGIN

    path = Path(path)
    tags = _XML_TAGS | {PLUGIN: "bsdf"}

    def numbers(values) -> str:
        return ", ".join(repr(float(v)) for v in values)

    def element(parent, name, value):
        if isinstance(value, LookAt):
            transform = ElementTree.SubElement(parent, "transform", name=name)
            ElementTree.SubElement(
                transform,
                "lookat",
                origin=numbers(value.origin),
                target=numbers(value.target),
                up=numbers(value.up),
            )
        elif isinstance(value, dict) and value.get("type") == "rgb":
            ElementTree.SubElement(parent, "rgb", name=name, value=numbers(value["value"]))
        elif isinstance(value, dict):
            if value.get("type") not in tags:
                raise ValueError(
                    f"{name}: no XML element for a plugin of type {value.get('type')!r}"
                )
            child = ElementTree.SubElement(parent, tags[value["type"]], type=value["type"])
            if tags[value["type"]] not in ("film", "sampler", "rfilter", "bsdf"):
                child.set("id", name)
            for key, item in value.items():
                if key != "type":
                    element(child, key, item)
        elif isinstance(value, bool):
            ElementTree.SubElement(parent, "boolean", name=name, value=str(value).lower())
        elif isinstance(value, int):
            ElementTree.SubElement(parent, "integer", name=name, value=str(value))
        elif isinstance(value, float):
            ElementTree.SubElement(parent, "float", name=name, value=repr(value))
        elif isinstance(value, str):
            if name == "filename":
                value = os.path.relpath(value, path.parent)
            ElementTree.SubElement(parent, "string", name=name, value=value)
        elif isinstance(value, list | tuple) and len(value) == 3:
            kind = "point" if name == "position" else "vector"
            ElementTree.SubElement(parent, kind, name=name, value=numbers(value))
        else:
            raise ValueError(
                f"{name}={value!r} cannot be written as Mitsuba XML "
                "(a BSDF object has no XML form: give it as a dict)"
            )

    root = ElementTree.Element("scene", version="3.0.0")
    for key, value in description.items():
        if key != "type":
            element(root, key, value)
    ElementTree.indent(root)
    path.write_text(ElementTree.tostring(root, encoding="unicode") + "\n")
    return path


def write_scene(
    out: str | os.PathLike, file: str | os.PathLike, scene: Scene, spp: int = 64
) -> Path:
    """Write ``scene`` with the compressed model ``file`` on its cloth into the folder
    ``out`` (module docstring); returns the path of ``scene.xml``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = out / MODEL_FILE
    if not (model.exists() and model.samefile(file)):
        shutil.copyfile(file, model)
    from pipeline.render.mitsuba_bsdf import PLUGIN

    bsdf = {"type": PLUGIN, "loader": LOADER, "filename": str(model.resolve())}
    return write_xml(scene_description(scene, out, bsdf, spp), out / SCENE_FILE)


def render(
    scene, spp: int | None = None, *, seed: int = 0, variant: str | None = None
) -> np.ndarray:
    """Render a Mitsuba scene and return its linear RGB image.

    Parameters
    ----------
    scene : a path to a scene file, a :func:`scene_description` dict, or a loaded
        ``mi.Scene``.
    spp : int or None
        Samples per pixel; None: the scene's sampler's.
    seed : int
        Seeds the sampler: renders with different seeds are independent.
    variant : str or None
        Set this Mitsuba variant first; None: keep the current one (or choose one,
        :func:`pipeline.render.mitsuba_bsdf.choose_variant`, when none is set).

    Returns
    -------
    ndarray of shape (height, width, 3), float32
    """
    from pipeline.render import mitsuba_bsdf

    mitsuba_bsdf.register(variant)
    import mitsuba as mi

    if spp is not None and (isinstance(spp, bool) or int(spp) != spp or spp < 1):
        raise ValueError(f"spp={spp!r} must be an integer >= 1 or None")
    if isinstance(scene, str | os.PathLike):
        scene = mi.load_file(str(scene))
    elif isinstance(scene, dict):
        scene = mi.load_dict(mitsuba_dict(scene))
    with mitsuba_bsdf.evaluated_calls():
        image = mi.render(scene, spp=int(spp or 0), seed=int(seed))
    return np.array(image, dtype=np.float32)[..., :3]


def main(argv: list[str] | None = None) -> Path:
    """Write the scene folder (and render or benchmark it); returns ``scene.xml``'s path."""
    args = COMMAND.parse_args(argv, parse)
    scene = fig8_scene(args.width, args.height, args.shape, floor=args.floor)
    path = write_scene(args.out, args.file, scene, args.spp)
    print(f"wrote {path} ({args.shape}, {args.width}x{args.height}, {args.spp} spp)")
    if args.render or args.bench:
        import mitsuba as mi

        from pipeline.btf.render.stage import write_images
        from pipeline.render.mitsuba_bsdf import register

        register(args.variant)
        started = time.perf_counter()
        loaded = mi.load_file(str(path))
        loading = time.perf_counter() - started
        image = render(loaded)
        seconds = time.perf_counter() - started - loading
        write_images(path.parent / "image", image, 1.0)
        print(
            f"Mitsuba {mi.__version__} {mi.variant()}: {seconds:.1f} s per frame "
            f"({args.width}x{args.height}, {args.spp} spp; loading the scene "
            f"{loading:.1f} s more): {path.parent / 'image.exr'}"
        )
    if args.bench:
        from pipeline.render.engine import render_with_stats

        reference, stats = render_with_stats(scene, material_from_file(args.file), args.spp, seed=0)
        rmse = float(np.sqrt(np.mean(np.square(image - reference, dtype=np.float64))))
        print(
            f"project renderer (Embree): {stats.seconds:.1f} s per frame; RMSE between "
            f"the two frames {rmse:.4g} (mean radiance {float(reference.mean()):.4g})"
        )
    return path


if __name__ == "__main__":
    main()
