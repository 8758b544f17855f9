"""Fig. 7 of the clustered Neural BTF paper: reference and reconstructed crops.

For each (light, view) pair from the settings, the measured pair nearest to it (the data
may hold any direction set: the UBO2003 81-grid has the paper's pairs, a UBO2014 file or
a Fibonacci set has others), and at that pair the reference image of the crop next to the
reconstruction of every model (Neural BTF and each k). The reference's title gives the
pair used and, where it is not the one asked for, the pair asked for. Models are read
back from the stage cache through the cache keys that each MLflow run recorded as tags.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure

from pipeline.btf import stages  # noqa: E402
from pipeline.btf.evaluate import decode_all  # noqa: E402
from pipeline.btf.model import load_decoder  # noqa: E402
from pipeline.btf.stereographic import direction_features  # noqa: E402
from pipeline.core.cache import StageCache  # noqa: E402
from pipeline.core.report import safe_stem, save_figure, write_file  # noqa: E402
from pipeline.data.directions import unit_vectors  # noqa: E402
from pipeline.data.images import gamma_encode, write_exr  # noqa: E402

log = logging.getLogger(__name__)


def nearest_direction(directions: np.ndarray, query: np.ndarray) -> int:
    """Index of the measured (light, view) pair closest to ``query`` (4,): the largest sum
    of the cosines of the light's and the view's angle to the query's. On a product of
    light and view sets: the nearest light under the nearest view."""
    light = unit_vectors(directions[:, 0], directions[:, 1]) @ unit_vectors(query[0], query[1])
    view = unit_vectors(directions[:, 2], directions[:, 3]) @ unit_vectors(query[2], query[3])
    return int(np.argmax(light + view))


def _degrees(angle: float) -> str:
    """An angle in radians as degrees: whole where it is (the UBO2003 grid), else 0.1."""
    degrees = float(np.degrees(angle))
    whole = round(degrees)
    return f"{whole:d}" if abs(degrees - whole) < 1e-6 else f"{degrees:.1f}"


def pair_label(pair: np.ndarray) -> str:
    """``l=(θ,φ) v=(θ,φ)`` in degrees of a direction pair (4,) in radians; φ in [0, 360).

    >>> pair_label(np.radians([30.0, 60.0, 15.0, 372.0]))
    'l=(30,60) v=(15,12)'
    """
    theta_l, phi_l, theta_v, phi_v = np.asarray(pair, dtype=np.float64)
    phi_l, phi_v = np.mod(phi_l, 2 * np.pi), np.mod(phi_v, 2 * np.pi)
    return f"l=({_degrees(theta_l)},{_degrees(phi_l)}) v=({_degrees(theta_v)},{_degrees(phi_v)})"


def _reconstruct(cache: StageCache, run: pd.Series, query: np.ndarray) -> np.ndarray | None:
    """(size, size, 3) reconstruction of one run at one direction, in normalized units."""
    trained = cache.lookup("train", str(run.get("tags.cache.train")))
    if trained is None:
        return None
    decoded = decode_all(
        load_decoder(trained.file("decoder.pt")),
        trained.array("latents", mmap=False),
        direction_features(query),
    )
    values = decoded[trained.array("latent_of_texel", mmap=False), 0]
    evaluated = cache.lookup("evaluate", str(run.get("tags.cache.evaluate")))
    if evaluated is not None and (evaluated.path / "texel_scale.npy").is_file():
        values = values * evaluated.array("texel_scale", mmap=False)[:, None]
    size = int(round(np.sqrt(len(values))))
    return values.reshape(size, size, 3)


def draw_fig7(runs: pd.DataFrame, pairs_degrees: list, out_dir: Path) -> list[Path]:
    """Draw one figure per dataset; returns the written files (PNG, EXR and JSON).

    runs : labelled runs (see :func:`pipeline.btf.tables.label_runs`), one model per column is drawn
        (the run with the lowest seed).
    pairs_degrees : list of [theta_l, phi_l, theta_v, phi_v] in degrees.

    Beside each figure, ``fig7_<dataset>_pairs.json`` lists per row the pair asked for and
    the measured pair used (``asked``, ``used``: degrees; ``column``: its index in the data).
    """
    written: list[Path] = []
    for stale in out_dir.glob("fig7_*"):  # figures of runs that are gone must not linger
        stale.unlink()
    queries = np.radians(np.asarray(pairs_degrees, dtype=np.float64).reshape(-1, 4))
    for dataset, group in runs.groupby("dataset"):
        group = group.sort_values(["order", "model", "seed"]).drop_duplicates("model")
        first = group.iloc[0]
        cache = StageCache(first["params.paths.cache"])
        crop = cache.lookup("crop", str(first.get("tags.cache.crop")))
        prep = cache.lookup("preprocess", str(first.get("tags.cache.preprocess")))
        if crop is None or prep is None:
            log.warning("fig7: cache entries of %s are gone; skipping its figure", dataset)
            continue
        abrdf, directions = stages.abrdf(crop), crop.array("directions", mmap=False)
        alpha = float(prep.json("alpha"))
        size = int(round(np.sqrt(abrdf.shape[0])))
        panels: list[list[tuple[str, np.ndarray]]] = []
        rows: list[dict] = []
        for query in queries:
            nearest = nearest_direction(directions, query)
            used = directions[nearest]
            rows.append(
                {
                    "asked": np.degrees(query).tolist(),
                    "used": np.degrees(used).tolist(),
                    "column": nearest,
                }
            )
            reference = np.asarray(abrdf[:, nearest]).reshape(size, size, 3) / alpha
            label = f"reference\n{pair_label(used)}"
            if pair_label(used) != pair_label(query):
                label += f"\n(asked {pair_label(query)})"
            row = [(label, reference)]
            for _, run in group.iterrows():
                # At the pair the reference shows, so that the panels compare one image.
                image = _reconstruct(cache, run, used[None])
                if image is not None:
                    row.append((run["model"], image))
            panels.append(row)
        safe = safe_stem(dataset)
        written.append(_plot(panels, out_dir / f"fig7_{safe}.png", dataset))
        written.append(out_dir / f"fig7_{safe}_pairs.json")
        write_file(written[-1], json.dumps(rows, indent=1))
        for i, row in enumerate(panels):
            for label, image in row:
                name = safe_stem(label.split("\n")[0])
                path = out_dir / f"fig7_{safe}_pair{i}_{name}.exr"
                write_exr(path, (image * alpha).astype(np.float32))
                written.append(path)
    return written


def _plot(panels, path: Path, title: str) -> Path:
    rows, cols = len(panels), max(len(r) for r in panels)
    fig = Figure(figsize=(2.2 * cols, 2.4 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for i, row in enumerate(panels):
        for j, (label, image) in enumerate(row):
            # Display: normalized linear values, gamma 2.2 like the UBO2003 JPEGs.
            axes[i, j].imshow(gamma_encode(np.clip(image, 0.0, 1.0)), interpolation="nearest")
            axes[i, j].set_title(label, fontsize=8)
    fig.suptitle(
        f"Fig. 7: reference vs reconstruction ({title})\nat the measured pair "
        f"nearest each one asked for",
        fontsize=10,
    )
    fig.tight_layout()
    save_figure(fig, path)
    return path
