"""``python -m benchmarks.render``: how long a Fig. 8 frame takes, and where the time goes.

Renders the default scene (:func:`pipeline.render.scene.default_scene`) once with each
material, at one size and spp, and prints seconds, rays per second and material queries per
second:

- ``lambertian``: a checkerboard albedo, nearly free to evaluate: the ray engine's share;
- ``measured``: the reference, interpolating a random crop of all 81 x 81 directions;
- ``neural``: a compressed BTF file with the paper's decoder and one latent per texel
  (random weights: the cost of a query does not depend on training);
- ``truth``: the built-in material's analytic generator (the ``render_truth`` stage);
- ``beyond grid``: the indicator that measures the share of samples beyond the measured grid
  (rendered once beside the reference).

The differences to ``lambertian`` are the materials' own cost. Figures are measured in the
one run, so compare them as ratios; on a shared machine absolute times move.

    python -m benchmarks.render size=256 spp=128 crop=100 threads=2

Settings are ``key=value`` (:data:`KEYS`; ``--help`` lists them), read before torch and
Embree are imported, so that a bad one is answered at once.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import cli
from pipeline.core.settings import Integer

PROG = "python -m benchmarks.render"


@dataclass(frozen=True)
class RenderBenchSettings:
    """The frame and material sizes; :data:`KEYS` describes each."""

    size: int = 256
    spp: int = 128
    crop: int = 100
    threads: int | None = None


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "size": ("size", Integer(1), "frame width and height, pixels"),
    "spp": ("spp", Integer(1), "samples per pixel"),
    "crop": ("crop", Integer(1), "texels per side of the BTF crop"),
    "threads": ("threads", Integer(1, optional=True), "torch threads (null: all cores)"),
}


COMMAND = cli.Command(
    PROG,
    KEYS,
    RenderBenchSettings,
    "The cost of a Fig. 8 frame per material. Settings and their defaults:",
    what="the render benchmark",
)
parse = COMMAND.parse  # raises ConfigError naming a bad argument (and the closest key)


def materials(crop: int, folder: Path, seed: int = 0) -> dict:
    """The benchmark materials for a crop x crop texture."""
    import torch

    from pipeline.btf.compressed import load_compressed, write_compressed
    from pipeline.btf.model import LATENT_DIM, Decoder
    from pipeline.btf.render.surfaces import (
        AnalyticMaterial,
        BeyondGridIndicator,
        CompressedMaterial,
        MeasuredMaterial,
    )
    from pipeline.btf.synthetic import SyntheticBTF
    from pipeline.data.directions import btf_directions
    from pipeline.render.materials import LambertianTexture

    rng = np.random.default_rng(seed)
    checker = (np.indices((crop, crop)).sum(0) % 2 * 0.6 + 0.2).astype(np.float32)
    torch.manual_seed(seed)
    path = write_compressed(
        folder / "btf.safetensors",
        Decoder(),
        rng.standard_normal((crop * crop, LATENT_DIM)).astype(np.float32),
        1.0,
        crop_size=(crop, crop),
        method="neural_btf",
        dataset="bench",
    )
    values = rng.random((crop * crop, 81 * 81, 3), dtype=np.float32)
    return {
        "lambertian": LambertianTexture(np.repeat(checker[..., None], 3, axis=2)),
        "measured": MeasuredMaterial(values, (crop, crop), btf_directions()),
        "neural": CompressedMaterial(load_compressed(path)),
        "truth": AnalyticMaterial(SyntheticBTF(size=max(crop, 2), seed=seed), (0, 0), (crop, crop)),
        "beyond grid": BeyondGridIndicator((crop, crop)),
    }


def main(argv: list[str] | None = None) -> dict:
    """Render each material once and print its figures; returns each one's render stats."""
    args = COMMAND.parse_args(argv)  # before torch and Embree load: errors come at once
    from pipeline.render.engine import render_with_stats
    from pipeline.render.scene import default_scene

    if args.threads is not None:
        import torch

        torch.set_num_threads(args.threads)

    scene = default_scene(args.size, args.size, floor=False)  # as btf.render.floor
    found = {}
    with tempfile.TemporaryDirectory() as tmp:
        chosen = materials(args.crop, Path(tmp))
        print(f"{args.size}x{args.size}, {args.spp} spp, crop {args.crop}^2, one point light")
        print(
            f"{'material':<11} {'seconds':>8} {'M rays/s':>9} {'M queries':>10} "
            f"{'M queries/s':>12} {'x lambertian':>13}"
        )
        for name, material in chosen.items():
            _, stats = render_with_stats(scene, material, args.spp, seed=0)
            found[name] = stats
            ratio = stats.seconds / found["lambertian"].seconds
            print(
                f"{name:<11} {stats.seconds:8.1f} {stats.rays_per_second / 1e6:9.2f} "
                f"{stats.material_queries / 1e6:10.2f} "
                f"{stats.material_queries / stats.seconds / 1e6:12.2f} {ratio:13.2f}"
            )
    return found


if __name__ == "__main__":
    main()
