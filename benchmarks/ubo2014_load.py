"""``python -m benchmarks.ubo2014_load [file=PATH]``: the peak memory of loading a UBO2014 crop.

Loads a crop the way the load stage does (into a ``.npy`` memory map) and prints its peak
memory: the heap peak (tracemalloc: what numpy allocated) and the peak resident set (which
also counts the pages of the memory-mapped file and output that were touched). Without
``file`` it writes a file of the UBO2014 shape first: 151 views × 151 lights, 400 × 400
texels, random float16 factors of ``components`` components::

    python -m benchmarks.ubo2014_load 'crop=[0,0,100,100]' components=64

Settings are ``key=value`` (:data:`KEYS`; ``--help`` lists them). A file's header, views and
lights: ``python -m pipeline.data.ubo2014_info file=PATH``.
"""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import cli
from pipeline.core.errors import ConfigError
from pipeline.core.files import human, reserved_memmap
from pipeline.core.memory import stage_peak
from pipeline.core.settings import Integer, ListOf, OneOf
from pipeline.data.ubo2014 import count_ubo2014_images, load_ubo2014
from pipeline.data.ubo2014_header import read_dfmf
from pipeline.data.ubo2014_write import write_dfmf

PROG = "python -m benchmarks.ubo2014_load"


@dataclass(frozen=True)
class UBO2014LoadSettings:
    """The file and the crop to load; :data:`KEYS` describes each."""

    file: str | None = None
    crop: tuple[int, ...] = (0, 0, 100, 100)
    components: int = 16
    dtype: str = "float16"
    workdir: str | None = None


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "file": (
        "file",
        cli.Text(optional=True),
        "a .btf (DFMF) file; without it one of the UBO2014 shape",
    ),
    "crop": ("crop", ListOf(Integer(0), 4), "[row, col, height, width] texels loaded"),
    "components": ("components", Integer(1), "components per channel of the written file"),
    "dtype": ("dtype", OneOf("float16", "float32"), "factors of the written file"),
    "workdir": (
        "workdir",
        cli.Text(optional=True),
        "where the written file and the decoded crop go (null: the temp dir)",
    ),
}


COMMAND = cli.Command(
    PROG,
    KEYS,
    UBO2014LoadSettings,
    "Peak memory of loading a crop (of file=, or of a file it writes). "
    "Settings and their defaults:",
    what="the load benchmark",
)


def hemisphere_angles(count: int, max_theta_deg: float = 75.0) -> np.ndarray:
    """``count`` (θ, φ) radians spread over the cap θ <= max_theta (a Fibonacci spiral),
    shape (count, 2)."""
    index = np.arange(count) + 0.5
    cos_theta = 1.0 - index / count * (1.0 - np.cos(np.radians(max_theta_deg)))
    phi = np.mod(index * np.pi * (3.0 - np.sqrt(5.0)), 2 * np.pi)
    return np.stack([np.arccos(cos_theta), phi], axis=1)


def parse(argv: list[str]) -> UBO2014LoadSettings:
    """:class:`UBO2014LoadSettings` from ``key=value`` arguments; raises
    :class:`ConfigError` naming a bad one."""
    given = cli.read(argv, KEYS, COMMAND.what)
    written = sorted({"components", "dtype"} & set(given))  # of the file the benchmark writes
    if given.get("file") is not None and written:
        raise ConfigError(
            f"{', '.join(written)}: settings of the file the benchmark writes, but "
            f"file= names one to read: give one or the other"
        )
    if "crop" in given:
        given["crop"] = tuple(given["crop"])
    return UBO2014LoadSettings(**given)


def write_paper_shaped(
    path: Path,
    components: int = 16,
    dtype: str = "float16",
    seed: int = 0,
    n_views: int = 151,
    n_lights: int = 151,
    size: int = 400,
) -> Path:
    """A DFMF file of the UBO2014 shape with random factors (colour model 0, cosine flag
    set); only its shape and layout matter, not its values."""
    rng = np.random.default_rng(seed)
    rows, columns = n_views * n_lights, size * size
    factors = [
        (
            np.ones(components),
            rng.standard_normal((rows, components)) / np.sqrt(components),
            rng.standard_normal((columns, components)),
        )
        for _ in range(3)
    ]
    return write_dfmf(
        path,
        hemisphere_angles(n_views),
        hemisphere_angles(n_lights),
        size,
        size,
        factors=factors,
        dtype=dtype,
        sync=False,
    )


def bench_crop_load(
    path: Path, workdir: Path, crop=(0, 0, 100, 100), views=None, lights=None
) -> dict:
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


def main(argv: list[str] | None = None) -> None:
    """Load the crop (of ``file``, or of a file of the UBO2014 shape written first) and
    print the file's size and the load's peaks."""
    args = COMMAND.parse_args(argv, parse)
    with tempfile.TemporaryDirectory(dir=args.workdir) as workdir:
        path = None if args.file is None else Path(args.file)
        if path is None:
            path = Path(workdir) / "paper_shaped.btf"
            write_paper_shaped(path, components=args.components, dtype=args.dtype)
        result = bench_crop_load(path, Path(workdir), crop=args.crop)
    print(f"file {path}: {human(result['file_bytes'])} (factors {human(result['factor_bytes'])})")
    print(f"crop {args.crop}: {result['n_images']} images, decoded {human(result['out_bytes'])}")
    print(
        f"heap peak {human(result['heap_peak_bytes'])}, "
        f"RSS peak {result['rss_peak_mb']:.0f} MiB, {result['seconds']:.1f} s"
    )


if __name__ == "__main__":
    main()
