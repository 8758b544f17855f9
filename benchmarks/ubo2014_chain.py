"""Method A's chain at UBO2014 scale, measured: ``python -m benchmarks.ubo2014_chain``.

Writes a file of the UBO2014 shape with *structured* values (:func:`write_structured`: a
built-in material at every one of the 151 x 151 directions, exactly of rank
``components``), or takes ``file=``, runs the main job's models on a ``size`` x ``size``
crop of it (one ``python -m pipeline`` job each, into ``workdir/runs``; PCA at the file's
own rank) and prints per model and stage the time, the peak resident set and the cache
bytes written::

    python -m benchmarks.ubo2014_chain size=100 workdir=/work/ubo_chain
    python -m benchmarks.ubo2014_chain size=400 models=[pca,clustered] workdir=/work/ubo_chain

Settings are ``key=value`` (:data:`KEYS`; ``--help`` lists them). Stages are cached in the
work folder, so a cut run resumes.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.ubo2014_load import hemisphere_angles
from pipeline.core import cli
from pipeline.core.cache import folder_bytes
from pipeline.core.files import human
from pipeline.core.settings import Integer, ListOf, OneOf
from pipeline.data.ubo2014_header import read_dfmf
from pipeline.data.ubo2014_write import factorize, write_dfmf

PROG = "python -m benchmarks.ubo2014_chain"
EXPERIMENT = "ubo2014_chain"  # the MLflow experiment the jobs log to


@dataclass(frozen=True)
class ChainSettings:
    """The command's settings; :data:`KEYS` describes each."""

    workdir: str | None = None
    file: str | None = None
    size: int = 100
    texture: int = 400
    components: int = 16
    models: tuple[str, ...] = ("neural_btf", "clustered", "pca")


KEYS = {
    "workdir": ("workdir", cli.Text(optional=True), "where the file, the runs and cache go (kept)"),
    "file": ("file", cli.Text(optional=True), "a .btf (DFMF) file; null: write a structured one"),
    "size": ("size", Integer(1), "texels per side of the crop (offset [0, 0]) the jobs run on"),
    "texture": ("texture", Integer(1), "texels per side of the written file"),
    "components": ("components", Integer(1), "rank of the written file's values per channel"),
    "models": (
        "models",
        ListOf(OneOf("neural_btf", "clustered", "pca")),
        "the main job's models to run, one job each",
    ),
}

COMMAND = cli.Command(PROG, KEYS, ChainSettings, "Method A's chain on a UBO2014-shaped file.")


def direction_pairs(views: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """(θ_l, φ_l, θ_v, φ_v) of every (view, light), view-major: a DFMF file's row order."""
    return np.concatenate(
        [np.tile(lights, (len(views), 1)), np.repeat(views, len(lights), axis=0)], axis=1
    )


def write_structured(
    path: Path,
    components: int = 16,
    dtype: str = "float16",
    material: str = "plain_weave",
    tile: int = 32,
    n_views: int = 151,
    n_lights: int = 151,
    size: int = 400,
) -> Path:
    """A DFMF file of the UBO2014 shape whose values are a material's, not noise: the
    built-in ``material`` (:class:`~pipeline.btf.synthetic.SyntheticBTF`) at every
    (view, light) of the file, on a ``tile`` x ``tile`` patch repeated over the texture
    with a smooth brightness gain that does not repeat (every texel distinct),
    factorised per channel to ``components`` (the file's values are exactly of that rank,
    so PCA of them is exact at ``components``). Colour model 0, cosine in the data.

    Only the patch is ever evaluated (n_views · n_lights x tile² values), never the
    n_views · n_lights x size² values the file decodes to."""
    from pipeline.btf.synthetic import SyntheticBTF

    views, lights = hemisphere_angles(n_views), hemisphere_angles(n_lights)
    fabric = SyntheticBTF(size=tile, seed=0, material=material)
    patch = fabric.evaluate(direction_pairs(views, lights))
    reps = -(-size // tile)
    rows, cols = np.mgrid[0:size, 0:size] / size
    gain = 1.0 + 0.15 * np.sin(2 * np.pi * (1.3 * rows + 0.7 * cols)) + 0.05 * np.cos(9.1 * rows)
    gain *= 1.0 + 0.05 * np.sin(23.7 * cols + 5.3 * rows)
    factors = []
    for channel in range(3):
        s_values, u, coefficients = factorize(
            patch[..., channel].reshape(len(patch), -1).astype(np.float64), components
        )
        # The patch's coefficients (image rows from the top) repeated over the texture, each
        # texel scaled by a smooth gain that does not repeat with the patch (so that no two
        # texels are equal, as in a measured material: k-means needs k distinct ABRDFs; a
        # scale keeps the rank), then put in the file's texel order (rows from the bottom).
        texture = np.tile(coefficients.reshape(tile, tile, -1), (reps, reps, 1))[:size, :size]
        texture = texture * gain[:, :, None]
        factors.append((s_values, u, texture[::-1].reshape(size * size, -1)))
    return write_dfmf(path, views, lights, size, size, factors=factors, dtype=dtype, sync=False)


def run_chain(
    path: Path, runs: Path, size: int, models=("neural_btf", "clustered", "pca"), offset=(0, 0)
):
    """Run ``models`` of the main job on ``size`` x ``size`` texels of ``path`` at
    ``offset`` (None: the default ``btf.crop.offset``), one job after the other, into the
    store ``runs``. Returns a dict per job and stage: ``model``, ``stage``, ``seconds``,
    ``rss_mb`` (the stage's peak resident set), ``cache_bytes`` (what that stage wrote in
    that job: 0 for a hit) and the job's ``rmse``.
    """
    import mlflow

    from pipeline.core.store import use_store

    rows = []
    # PCA at the file's own rank (its components summed over the channels), in float32: the
    # data are exactly of that rank, so PCA should reconstruct them up to rounding (the
    # main job's PCA at the bytes of k = 128 holds no component at 22,801 directions).
    rank = sum(channel.components for channel in read_dfmf(path).channels)
    pca = ["model.match_clustered_k=null", f"model.n_components={rank}", "model.dtype=float32"]
    crop = [f"btf.crop.size={size}"]
    if offset is not None:
        crop.append(f"btf.crop.offset=[{offset[0]},{offset[1]}]")
    for model in models:
        before = {d.name: folder_bytes(d) for d in (runs / "cache").glob("*")}
        command = [sys.executable, "-m", "pipeline", "dataset=ubo2014", f"dataset.root={path}"]
        command += [*crop, f"model={model}", *(pca if model == "pca" else [])]
        command += [f"paths.runs={runs}", f"tracking.experiment={EXPERIMENT}"]
        if subprocess.run(command).returncode != 0:  # the job has said why, in one line
            print(f"{PROG}: the {model} job failed; the other models go on", file=sys.stderr)
            continue
        use_store(str(runs))
        run = mlflow.search_runs(
            experiment_names=[EXPERIMENT],
            output_format="list",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )[0]
        metrics = run.data.metrics
        for name, seconds in metrics.items():
            if not (name.startswith("time/") and name.endswith("_seconds")):
                continue
            stage = name.removeprefix("time/").removesuffix("_seconds")
            row = {"model": model, "stage": stage, "seconds": seconds}
            row["rss_mb"] = metrics.get(f"memory/{stage}_peak_rss_mb", float("nan"))
            row["cache_bytes"] = folder_bytes(runs / "cache" / stage) - before.get(stage, 0)
            rmse = {key: metrics.get(key) for key in ("rmse", "rmse_mean_abrdf")}
            rows.append({**row, **rmse})
    return rows


def main(argv: list[str] | None = None) -> None:
    args = COMMAND.parse_args(argv)
    if args.workdir is None:
        raise SystemExit(f"{PROG}: error: workdir=PATH is needed (the file and runs are kept)")
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    path = Path(args.file) if args.file else None
    if path is None:
        path = workdir / f"structured_{args.texture}_c{args.components}.btf"
        if not path.exists():
            write_structured(path, args.components, size=args.texture)
    dfmf = read_dfmf(path)
    if args.size > min(dfmf.height, dfmf.width):
        raise SystemExit(f"{PROG}: error: size={args.size} is larger than the texture: {path}")
    decoded = args.size**2 * dfmf.n_directions * 3 * 4
    print(f"file {path}: {human(dfmf.size)}; its {args.size}² crop decoded: {human(decoded)}")
    rows = run_chain(path, workdir / "runs", args.size, args.models)
    print(f"{'model':<11} {'stage':<16} {'seconds':>9} {'peak RSS':>12} {'cache written':>14}")
    for row in rows:
        print(
            f"{row['model']:<11} {row['stage']:<16} {row['seconds']:9.1f} "
            f"{row['rss_mb']:8.0f} MiB {human(row['cache_bytes']):>14}"
        )
    for model in args.models:
        mine = [row for row in rows if row["model"] == model]
        if not mine:
            continue
        written = sum(row["cache_bytes"] for row in mine)
        print(
            f"{model}: RMSE {mine[0]['rmse']:.4f} (mean ABRDF {mine[0]['rmse_mean_abrdf']:.4f}), "
            f"{sum(r['seconds'] for r in mine):.0f} s in stages, cache written {human(written)} "
            f"({written / decoded:.2f} x the decoded crop)"
        )


if __name__ == "__main__":
    main()
