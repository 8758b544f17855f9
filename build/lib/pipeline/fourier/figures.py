"""Method C's figures: held-out relighting, segmentation, normals (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.report import save_figure
from pipeline.fourier.series import rms_error


def display(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB -> sRGB-encoded values in [0, 1] for PNG figures."""
    from pipeline.data.images import srgb_oetf

    return srgb_oetf(np.clip(np.asarray(linear) * exposure, 0.0, 1.0))


def segmentation_figure(path: Path, mean, truth, labels: dict) -> None:
    from matplotlib.figure import Figure

    panels = [("mean image", display(mean / max(float(mean.max()), 1e-12)))]
    if truth is not None:
        panels.append(("ground truth", truth))
    panels += [(f"{name}", found) for name, found in labels.items()]
    fig = Figure(figsize=(3 * len(panels), 3.2))
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, (title, image) in zip(axes[0], panels, strict=True):
        ax.imshow(image, cmap="tab10", vmin=0, vmax=9, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def heldout_figure(path: Path, rows: dict, dirs: np.ndarray, exposure: float) -> None:
    from matplotlib.figure import Figure

    reference = rows["reference"]
    names = list(rows)
    fig = Figure(figsize=(2.4 * len(names), 2.5 * len(dirs)))
    axes = fig.subplots(len(dirs), len(names), squeeze=False)
    for i, light in enumerate(dirs):
        for j, name in enumerate(names):
            ax = axes[i, j]
            ax.imshow(display(rows[name][i], exposure), interpolation="nearest")
            if name == "reference":
                label = "reference, l = ({:.2f}, {:.2f}, {:.2f})".format(*light)
            else:
                label = f"{name}  RMS {rms_error(rows[name][i], reference[i]):.4f}"
            ax.set_title(label, fontsize=8)
            ax.axis("off")
    fig.suptitle("held-out lights: reference and relit models", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def normals_figure(path: Path, normals: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.round((normals * 0.5 + 0.5) * 255).astype(np.uint8)).save(path)
