"""Fig. 7 of the clustered Neural BTF paper: reference and reconstructed crops.

For each (light, view) pair from the settings, the measured pair nearest to it (the data
may hold any direction set: the UBO2003 81-grid has the paper's pairs, a UBO2014 file or
a Fibonacci set has others), and at that pair the reference image of the crop next to the
reconstruction of every model (Neural BTF and each k). The reference's title gives the
pair used and, where it is not the one asked for, the pair asked for. Each job logs its
panels (:func:`job_data`) and the tables draw from what the runs logged: the cache may be
cleared without losing the figure.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from pipeline.btf import stages
from pipeline.btf.evaluate import decode_all
from pipeline.btf.model import load_decoder
from pipeline.btf.stereographic import direction_features
from pipeline.core.cache import Entry
from pipeline.core.report import first_with_data, logged_arrays, safe_stem, save_figure, write_file
from pipeline.data.directions import unit_vectors
from pipeline.data.images import gamma_encode, write_exr

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


DATA_NAME = "fig7_data.npz"  # what a job logs under figures/ and the tables draw from


def _reconstruct(trained: Entry, evaluated: Entry | None, query: np.ndarray) -> np.ndarray:
    """(size, size, 3) reconstruction of a trained model at one direction, normalized."""
    decoded = decode_all(
        load_decoder(trained.file("decoder.pt")),
        trained.array("latents", mmap=False),
        direction_features(query),
    )
    values = decoded[trained.array("latent_of_texel", mmap=False), 0]
    if evaluated is not None and (evaluated.path / "texel_scale.npy").is_file():
        values = values * evaluated.array("texel_scale", mmap=False)[:, None]
    size = int(round(np.sqrt(len(values))))
    return values.reshape(size, size, 3)


def job_data(
    cropped: Entry, prep: Entry, trained: Entry, evaluated: Entry | None, pairs_degrees: list
) -> dict[str, np.ndarray]:
    """One job's Fig. 7: at the measured pair nearest each pair asked for (degrees), the
    reference crop and the model's reconstruction, normalized (divided by ``alpha``).

    Returns ``asked``, ``used`` (P, 4 degrees), ``column`` (P,: the pair's index in the
    data), ``reference`` and ``model`` (P, size, size, 3) and ``alpha``: what the job logs as
    :data:`DATA_NAME`."""
    abrdf, directions = stages.abrdf(cropped), cropped.array("directions", mmap=False)
    alpha = float(prep.json("alpha"))
    size = int(round(np.sqrt(abrdf.shape[0])))
    queries = np.radians(np.asarray(pairs_degrees, dtype=np.float64).reshape(-1, 4))
    columns = np.array([nearest_direction(directions, q) for q in queries], dtype=np.int64)
    reference = np.stack(
        [np.asarray(abrdf[:, c]).reshape(size, size, 3) / np.float32(alpha) for c in columns]
    )
    model = np.stack([_reconstruct(trained, evaluated, directions[c][None]) for c in columns])
    return {
        "asked": np.degrees(queries),
        "used": np.degrees(directions[columns]),
        "column": columns,
        "reference": reference.astype(np.float32),
        "model": model.astype(np.float32),
        "alpha": np.float64(alpha),
    }


def logged_data(run_id: str) -> dict[str, np.ndarray] | None:
    """The Fig. 7 data a run logged (``figures/fig7_data.npz``), or None."""
    return logged_arrays(run_id, f"figures/{DATA_NAME}")


def draw_fig7(runs: pd.DataFrame, out_dir: Path, data_of=logged_data) -> list[Path]:
    """Draw one figure per dataset from what the runs logged (:func:`job_data`); returns
    the written files (PNG, EXR and JSON).

    runs : labelled runs (see :func:`pipeline.btf.tables.label_runs`), one model per column
        is drawn (the run with the lowest seed); PCA's runs (no decoder) are left out, and
        so, with a warning, are runs that logged no Fig. 7 data or other pairs than the
        first one's.
    data_of : run id -> its data (:func:`logged_data`); a job passes its own.

    Beside each figure, ``fig7_<dataset>_pairs.json`` lists per row the pair asked for and
    the measured pair used (``asked``, ``used``: degrees; ``column``: its index in the data).
    """
    from pipeline.btf.models import models_of

    written: list[Path] = []
    for stale in out_dir.glob("fig7_*"):  # figures of runs that are gone must not linger
        stale.unlink()
    # Models with a decoder to query: PCA has none, and draws no panel.
    runs = runs[[m is not None and m.stage is not None for m in models_of(runs)]]
    for dataset, group in runs.groupby("dataset"):
        group = group.sort_values(["order", "model", "seed"])
        shown: list[tuple[str, dict]] = []
        for model, data in first_with_data(group, data_of, f"fig7 of {dataset}", log):
            if shown and not np.array_equal(data["asked"], shown[0][1]["asked"]):
                log.warning("fig7: %s was drawn at other pairs; left out", model)
                continue
            shown.append((model, data))
        if not shown:
            log.warning("fig7: no run of %s logged its Fig. 7 data; skipping it", dataset)
            continue
        first = shown[0][1]
        rows = [
            {"asked": a.tolist(), "used": u.tolist(), "column": int(c)}
            for a, u, c in zip(first["asked"], first["used"], first["column"], strict=True)
        ]
        panels: list[list[tuple[str, np.ndarray]]] = []
        for i, row in enumerate(rows):
            used, asked = (pair_label(np.radians(row[key])) for key in ("used", "asked"))
            label = f"reference\n{used}" + (f"\n(asked {asked})" if asked != used else "")
            # At the pair the reference shows, so that the panels compare one image.
            panels.append([(label, first["reference"][i])] + [(m, d["model"][i]) for m, d in shown])
        safe = safe_stem(dataset)
        written.append(_plot(panels, out_dir / f"fig7_{safe}.png", dataset))
        written.append(out_dir / f"fig7_{safe}_pairs.json")
        write_file(written[-1], json.dumps(rows, indent=1))
        alpha = float(first["alpha"])
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
