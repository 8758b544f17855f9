"""``python -m pipeline.data.ubo2014_bench info file=PATH`` and ``... bench [file=PATH]``.

``info`` prints a DFMF file's header facts and its view and light directions with the
indices ``dataset.views`` / ``dataset.lights`` accept. ``bench`` loads a crop the way the
load stage does (into a ``.npy`` memory map) and prints its peak memory: the heap peak
(tracemalloc: what numpy allocated) and the peak resident set (which also counts the
pages of the memory-mapped file and output that were touched). Without ``file`` it writes
a file of the UBO2014 shape first: 151 views × 151 lights, 400 × 400 texels, random
float16 factors of ``components`` components::

    python -m pipeline.data.ubo2014_bench bench 'crop=[0,0,100,100]' components=64

Settings are ``key=value`` after the command (:data:`KEYS`; ``--help`` lists them).
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
from pipeline.data.ubo2014_header import describe, read_dfmf
from pipeline.data.ubo2014_write import write_dfmf

PAPER_SHAPE = {"n_views": 151, "n_lights": 151, "size": 400}
PROG = "python -m pipeline.data.ubo2014_bench"
COMMANDS = {
    "info": "header facts, views and lights of the .btf file (file= required)",
    "bench": "peak memory of loading a crop (of file=, or of a file it writes)",
}


@dataclass(frozen=True)
class UBO2014BenchSettings:
    """The command and its settings; :data:`KEYS` describes each."""

    command: str = "bench"
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
        "a .btf (DFMF) file; bench without it writes one of the UBO2014 shape",
    ),
    "crop": ("crop", ListOf(Integer(0), 4), "[row, col, height, width] texels loaded (bench)"),
    "components": ("components", Integer(1), "components per channel of the written file (bench)"),
    "dtype": ("dtype", OneOf("float16", "float32"), "factors of the written file (bench)"),
    "workdir": (
        "workdir",
        cli.Text(optional=True),
        "where the written file and the decoded crop go (null: the temp dir; bench)",
    ),
}


COMMAND = cli.Command(
    PROG,
    KEYS,
    UBO2014BenchSettings,
    "\n".join(f"  {name:<6} {text}" for name, text in COMMANDS.items())
    + "\n\nSettings and their defaults:",
    synopsis=f"{{{','.join(COMMANDS)}}} [key=value ...]",
)


def parse(argv: list[str]) -> UBO2014BenchSettings:
    """:class:`UBO2014BenchSettings` from the command and its ``key=value`` arguments;
    raises :class:`ConfigError` naming a bad one."""
    command, rest = cli.command_of(argv, list(COMMANDS))
    given = cli.read(rest, KEYS, f"the {command} command")
    written = sorted({"components", "dtype"} & set(given))  # settings of the file bench writes
    if command == "info":
        if given.get("file") is None:
            raise ConfigError("info needs file=PATH, the .btf file to describe")
        if others := sorted(set(given) - {"file"}):
            raise ConfigError(f"{', '.join(others)}: settings of bench, not of info")
    elif given.get("file") is not None and written:
        raise ConfigError(
            f"{', '.join(written)}: settings of the file bench writes, but "
            f"file= names one to read: give one or the other"
        )
    if "crop" in given:
        given["crop"] = tuple(given["crop"])
    return UBO2014BenchSettings(command, **given)


def hemisphere_angles(count: int, max_theta_deg: float = 75.0) -> np.ndarray:
    """``count`` (θ, φ) radians spread over the cap θ <= max_theta (a Fibonacci spiral),
    shape (count, 2)."""
    index = np.arange(count) + 0.5
    cos_theta = 1.0 - index / count * (1.0 - np.cos(np.radians(max_theta_deg)))
    phi = np.mod(index * np.pi * (3.0 - np.sqrt(5.0)), 2 * np.pi)
    return np.stack([np.arccos(cos_theta), phi], axis=1)


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


def _bench(args: UBO2014BenchSettings) -> None:
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


def main(argv: list[str] | None = None) -> None:
    args = COMMAND.parse_args(argv, parse)
    if args.command == "info":
        _info(Path(args.file))
    else:
        _bench(args)


if __name__ == "__main__":
    main()
