"""Fig. 8 and Tables 3-4 of the clustering paper, from the runs of ``experiment=render``.

Tables 3 and 4 are the RMSE of the dark and the bright crop of each model's render against
the reference render (the measured BTF), mean ± std over seeds, at the largest samples per
pixel; the graininess table follows both crops through every spp, with the ratio of
high-frequency energy to the reference's (above 1: the model adds grain); the cloth table
gives the RMSE over every lit-cloth pixel at every spp. Fig. 8 is the
grid of renders (reference, Neural BTF, each k, PCA) of one seed with both crops marked, and
the crops enlarged below. Images are read back from the stage cache through the cache keys
the MLflow runs recorded (``tags.cache.render``, ``tags.cache.render_reference``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from pipeline.btf import tables
from pipeline.core.cache import StageCache
from pipeline.core.report import runs_of, safe_stem, write_table
from pipeline.data.images import gamma_encode, write_exr
from pipeline.render import RENDERED
from pipeline.render.stage import REGIONS

log = logging.getLogger(__name__)

COLOURS = {"dark": "tab:cyan", "bright": "tab:orange"}


def rendered_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """Labelled runs (:func:`pipeline.btf.tables.label_runs`) that rendered, one per render
    (a rerun that found its render cached records the same numbers again)."""
    if "metrics.render_rmse_dark" not in runs:
        return runs.iloc[0:0]
    runs = runs[runs["metrics.render_rmse_dark"].notna()]
    key = runs.get("tags.cache.render", runs["run_id"]).fillna(runs["run_id"])
    return runs.loc[~key.duplicated()]


def spp_levels(runs: pd.DataFrame) -> list[int]:
    """The samples-per-pixel levels of which the runs logged metrics."""
    prefix = "metrics.render_rmse_dark_spp"
    return sorted(int(c[len(prefix):]) for c in runs.columns if c.startswith(prefix))


def table_graininess(runs: pd.DataFrame) -> pd.DataFrame:
    """Rows (dataset, model, spp): both crops' RMSE and high-frequency energy ratio."""
    rows = []
    for spp in spp_levels(runs):
        for (dataset, model), group in runs.groupby(["dataset", "model"], sort=False):
            row = {"dataset": dataset, "model": model, "spp": spp}
            for region in REGIONS:
                rmse = group.get(f"metrics.render_rmse_{region}_spp{spp}")
                hf = group.get(f"metrics.render_hf_ratio_{region}_spp{spp}")
                if rmse is None or hf is None:
                    continue
                row[f"{region}: RMSE"] = tables.mean_std(rmse)
                row[f"{region}: HF energy / reference"] = tables.mean_std(hf)
            rows.append(row)
    if not rows:
        return pd.DataFrame()
    order = {m: i for i, m in enumerate(tables.model_columns(runs))}
    table = pd.DataFrame(rows)
    return table.sort_values(["dataset", "spp", "model"],
                             key=lambda s: s.map(order) if s.name == "model" else s)


def table_cloth(runs: pd.DataFrame) -> pd.DataFrame:
    """Rows (dataset, spp) x model columns: the RMSE over every pixel wholly on lit cloth,
    mean ± std over seeds; a larger sample than the crops, so a steadier ranking."""
    parts = [tables.table_rmse(runs, f"render_rmse_cloth_spp{spp}").assign(spp=spp)
             for spp in spp_levels(runs) if f"metrics.render_rmse_cloth_spp{spp}" in runs]
    if not parts:
        return pd.DataFrame()
    table = pd.concat(parts).reset_index().fillna("–")  # a model not rendered at that spp
    return table[["dataset", "spp", *[c for c in table.columns if c not in ("dataset", "spp")]]]


def sections(runs: pd.DataFrame, out: Path, settings=None) -> list[str]:
    """Tables 3-4, the lit-cloth RMSE and the graininess per spp, and Fig. 8 (when the
    cache is at hand), from MLflow's runs of every method; nothing when no run rendered."""
    runs = runs_of(runs, RENDERED)
    if runs.empty or "metrics.render_rmse_dark" not in runs:
        return []
    runs = rendered_runs(tables.label_runs(runs[runs["metrics.render_rmse_dark"].notna()]))
    found = []
    note = ("RMSE of linear radiance (the key light gives irradiance 1 at the sheet's centre, "
            "so values are in the BTF's units) against the reference render of the measured "
            "BTF, same scene, samples and seed; mean ± std over seeds (n), at "
            f"{spp_levels(runs)[-1]} samples per pixel. The crops are marked in Fig. 8.")
    for number, region in ((3, "dark"), (4, "bright")):
        table = tables.table_rmse(runs, f"render_rmse_{region}")
        found.append(write_table(table, out, f"table{number}_render_{region}",
                                 f"Table {number}: RMSE of the rendered {region} crop", note))
    cloth = table_cloth(runs)
    if not cloth.empty:
        found.append(write_table(
            cloth, out, "render_cloth", "RMSE of the render over the whole lit cloth",
            "As Tables 3-4, over every pixel whose camera samples all land on cloth that a "
            "light sees (no silhouette, shadow or floor pixels), at each samples-per-pixel level."))
    grain = table_graininess(runs)
    if not grain.empty:
        found.append(write_table(
            grain, out, "render_graininess", "Does the graininess survive rendering?",
            "Each crop at every samples-per-pixel level: RMSE against the reference and the "
            "high-frequency energy (image minus its Gaussian blur, sigma 1 pixel) of the "
            "model's crop over the reference's: above 1 the model adds grain, near 1 it has "
            "the reference's texture, below 1 it is smoother. Pixel samples are shared with "
            "the reference, so what differs is the BTF alone."))
    files = draw_fig8(runs, out)
    if files:
        found.append("## Fig. 8: renders\n\n" + "\n".join(
            f"![{p.stem}]({p.name})" for p in files if p.suffix == ".png") + "\n")
    return found


def draw_fig8(runs: pd.DataFrame, out: Path) -> list[Path]:
    """One figure per dataset (the lowest seed's renders at the largest spp): PNG, and an
    EXR of each render; returns the written files. Images come from the runs' stage cache
    (``params.paths.cache``); a dataset whose entries are gone is skipped with a warning."""
    for stale in out.glob("fig8_*"):
        stale.unlink()
    written = []
    for dataset, group in runs.groupby("dataset"):
        group = group.sort_values(["seed"]).drop_duplicates("model")
        group = group.sort_values("order")
        cache = StageCache(group["params.paths.cache"].iloc[0])
        reference = cache.lookup("render_reference",
                                 str(group["tags.cache.render_reference"].iloc[0]))
        if reference is None:
            log.warning("Fig. 8 of %s: its reference render is not in the cache", dataset)
            continue
        crops = reference.json("crops")
        levels = sorted(int(s) for s in reference.manifest["summary"]["spp"])
        spp = levels[-1]
        size = int(float(group["params.btf.render.crop_size"].iloc[0]))
        entries = [("reference", reference)]
        for _, run in group.iterrows():
            entry = cache.lookup("render", str(run.get("tags.cache.render")))
            if entry is not None:
                entries.append((run["model"], entry))
        by_spp = {s: [(name, e.array(f"image_spp{s}", mmap=False)) for name, e in entries]
                  for s in levels}
        panels = by_spp[spp]
        stem = "fig8_" + safe_stem(dataset)
        exposure = float(group["params.btf.render.exposure"].iloc[0])
        seed = int(group["seed"].min())
        written.append(_grid(panels, crops, size, exposure, f"{dataset}, {spp} spp, seed {seed}",
                             out / f"{stem}.png"))
        written.append(_crops_per_spp(by_spp, crops, size, f"{dataset}, seed {seed}",
                                      out / f"{stem}_crops_per_spp.png"))
        for name, image in panels:
            path = out / f"{stem}_{safe_stem(name)}.exr"
            write_exr(path, image)
            written.append(path)
    return written


def _grid(panels, crops: dict, size: int, exposure: float, title: str, path: Path) -> Path:
    """Renders in a row, both crops marked, each crop enlarged below its render."""
    columns = len(panels)
    fig = Figure(figsize=(2.4 * columns, 2.4 * 2 + 0.4))
    axes = fig.subplots(3, columns, squeeze=False,
                        gridspec_kw={"height_ratios": [2, 1, 1]})
    for column, (name, image) in enumerate(panels):
        shown = gamma_encode(image * np.float32(exposure))
        axes[0, column].imshow(shown, interpolation="nearest")
        axes[0, column].set_title(name, fontsize=9)
        for row, region in enumerate(REGIONS, start=1):
            r, c = crops[region]
            axes[0, column].add_patch(Rectangle((c - 0.5, r - 0.5), size, size, fill=False,
                                                edgecolor=COLOURS[region], linewidth=1.2))
            axes[row, column].imshow(shown[r : r + size, c : c + size], interpolation="nearest")
            axes[row, column].set_ylabel(region if column == 0 else "", fontsize=8,
                                         color=COLOURS[region])
    for axis in axes.ravel():
        axis.set_xticks([])
        axis.set_yticks([])
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _crops_per_spp(by_spp: dict, crops: dict, size: int, title: str, path: Path) -> Path:
    """Both crops of every render at every spp, side by side: one row per (region, spp),
    one column per render, to see whether a model's grain outlives the pixel's samples.
    Each region is exposed so that the reference's crop at the largest spp has its 99th
    percentile at white (the dark crop would be black at the frame's exposure); a row's
    renders share it."""
    levels = sorted(by_spp)
    columns = len(by_spp[levels[-1]])
    fig = Figure(figsize=(1.6 * columns + 0.6, 1.6 * 2 * len(levels) + 0.4))
    axes = fig.subplots(2 * len(levels), columns, squeeze=False)
    for block, region in enumerate(REGIONS):
        r, c = crops[region]
        reference = by_spp[levels[-1]][0][1][r : r + size, c : c + size]
        exposure = 1.0 / max(float(np.percentile(reference, 99)), 1e-6)
        for offset, spp in enumerate(levels):
            row = block * len(levels) + offset
            for column, (name, image) in enumerate(by_spp[spp]):
                shown = gamma_encode(image[r : r + size, c : c + size] * np.float32(exposure))
                axes[row, column].imshow(np.clip(shown, 0, 1), interpolation="nearest")
                if row == 0:
                    axes[row, column].set_title(name, fontsize=8)
            axes[row, 0].set_ylabel(f"{region}, {spp} spp", fontsize=8, color=COLOURS[region])
    for axis in axes.ravel():
        axis.set_xticks([])
        axis.set_yticks([])
    fig.suptitle(f"{title}\nthe crops at each samples-per-pixel level", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
