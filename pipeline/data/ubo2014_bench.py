"""``python -m pipeline.data.ubo2014_bench info FILE`` and ``... bench [FILE]``.

``info`` prints a DFMF file's header facts and its view and light directions with the
indices ``dataset.views`` / ``dataset.lights`` accept. ``bench`` loads a crop the way the
load stage does (into a ``.npy`` memory map) and prints its peak memory: the heap peak
(tracemalloc: what numpy allocated) and the peak resident set (which also counts the
pages of the memory-mapped file and output that were touched). Without FILE it writes a
file of the UBO2014 shape first: 151 views × 151 lights, 400 × 400 texels, random
float16 factors of ``--components`` components.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from pipeline.core.files import human, reserved_memmap
from pipeline.core.memory import stage_peak
from pipeline.data.ubo2014 import count_ubo2014_images, describe, load_ubo2014, read_dfmf
from pipeline.data.ubo2014_write import write_dfmf

PAPER_SHAPE = {"n_views": 151, "n_lights": 151, "size": 400}


def hemisphere_angles(count: int, max_theta_deg: float = 75.0) -> np.ndarray:
    """``count`` (θ, φ) radians spread over the cap θ <= max_theta (a Fibonacci spiral),
    shape (count, 2)."""
    index = np.arange(count) + 0.5
    cos_theta = 1.0 - index / count * (1.0 - np.cos(np.radians(max_theta_deg)))
    phi = np.mod(index * np.pi * (3.0 - np.sqrt(5.0)), 2 * np.pi)
    return np.stack([np.arccos(cos_theta), phi], axis=1)


def write_paper_shaped(path: Path, components: int = 16, dtype: str = "float16",
                       seed: int = 0, n_views: int = 151, n_lights: int = 151,
                       size: int = 400) -> Path:
    """A DFMF file of the UBO2014 shape with random factors (colour model 0, cosine flag
    set); only its shape and layout matter, not its values."""
    rng = np.random.default_rng(seed)
    rows, columns = n_views * n_lights, size * size
    factors = [
        (np.ones(components), rng.standard_normal((rows, components)) / np.sqrt(components),
         rng.standard_normal((columns, components)))
        for _ in range(3)
    ]
    return write_dfmf(path, hemisphere_angles(n_views), hemisphere_angles(n_lights), size, size,
                      factors=factors, dtype=dtype, sync=False)


def bench_crop_load(path: Path, workdir: Path, crop=(0, 0, 100, 100), views=None,
                    lights=None) -> dict:
    """Load ``crop`` of ``path`` into ``workdir/images.npy`` as the load stage does.

    Returns
    -------
    dict
        ``n_images``, ``out_bytes`` (the decoded crop), ``file_bytes``, ``factor_bytes``
        (U and SV of every channel: what a whole-file read would hold), ``heap_peak_bytes``
        (tracemalloc), ``rss_peak_mb`` and ``seconds``.
    """
    n, height, width = count_ubo2014_images(path, views, lights, crop)
    dfmf = read_dfmf(path)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with stage_peak() as peak:
            out = reserved_memmap(Path(workdir) / "images.npy", (n, height, width, 3), np.float32)
            load_ubo2014(path, views, lights, crop, out=out)
            out.flush()
            del out
        _, heap_peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return {
        "n_images": n,
        "out_bytes": n * height * width * 3 * 4,
        "file_bytes": dfmf.size,
        "factor_bytes": sum(c.end - c.offset for c in dfmf.channels),
        "heap_peak_bytes": heap_peak,
        "rss_peak_mb": peak["mb"],
        "seconds": time.perf_counter() - start,
    }


def _info(path: Path) -> None:
    dfmf = read_dfmf(path)
    for key, value in describe(dfmf).items():
        print(f"{key:>18}: {value}")
    print("views (index: theta, phi in degrees):")
    for index, (theta, phi) in enumerate(np.degrees(dfmf.view_angles)):
        print(f"  {index:4d}: {theta:7.2f} {phi:7.2f}")
    print("lights of view 0 (index: theta, phi in degrees):")
    for index, (theta, phi) in enumerate(np.degrees(dfmf.light_angles[0])):
        print(f"  {index:4d}: {theta:7.2f} {phi:7.2f}")


def _bench(args) -> None:
    with tempfile.TemporaryDirectory(dir=args.workdir) as workdir:
        path = args.file
        if path is None:
            path = Path(workdir) / "paper_shaped.btf"
            write_paper_shaped(path, components=args.components, dtype=args.dtype)
        result = bench_crop_load(path, Path(workdir), crop=args.crop)
    print(f"file {path}: {human(result['file_bytes'])} "
          f"(factors {human(result['factor_bytes'])})")
    print(f"crop {args.crop}: {result['n_images']} images, decoded {human(result['out_bytes'])}")
    print(f"heap peak {human(result['heap_peak_bytes'])}, "
          f"RSS peak {result['rss_peak_mb']:.0f} MiB, {result['seconds']:.1f} s")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.data.ubo2014",
                                     description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    info = commands.add_parser("info", help="header facts, views and lights of a .btf file")
    info.add_argument("file", type=Path)
    bench = commands.add_parser("bench", help="peak memory of loading a crop")
    bench.add_argument("file", type=Path, nargs="?",
                       help="a .btf file; default: write one of the UBO2014 shape")
    bench.add_argument("--crop", type=int, nargs=4, default=[0, 0, 100, 100],
                       metavar=("ROW", "COL", "HEIGHT", "WIDTH"))
    bench.add_argument("--components", type=int, default=16,
                       help="components per channel of the written file")
    bench.add_argument("--dtype", default="float16", choices=["float16", "float32"])
    bench.add_argument("--workdir", type=Path, default=None,
                       help="where the written file and the decoded crop go "
                       "(default: the temp dir)")
    args = parser.parse_args(argv)
    if args.command == "info":
        _info(args.file)
    else:
        _bench(args)


if __name__ == "__main__":
    main()
