"""Fig. 8 and Tables 3-4 of the clustering paper, from the runs of ``experiment=render``.

Tables 3 and 4 are the RMSE of the dark and the bright crop of each model's render, mean ±
std over seeds, at the largest samples per pixel; the graininess table follows both crops
through every spp, with the ratio of high-frequency energy to the target's (above 1: the
model adds grain); the cloth table gives the RMSE over every lit-cloth pixel at every spp.

Rows are scored against the analytic truth where a dataset's runs have it, else against the
measured reference (:func:`scored_runs`); each table says which in its caption and a
``scored against`` column, and gives the share of samples beyond the measured grid.

Fig. 8 is the grid of renders (truth when there is one, reference, Neural BTF, each k, PCA)
of one seed with both crops marked, and the crops enlarged below. Images are what the runs
logged (``render/fig8_data.npz``), so the cache may be cleared without losing the figure.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from pipeline.btf import tables
from pipeline.btf.render import RENDERED
from pipeline.btf.render.stage import REGIONS
from pipeline.core.report import (
    first_with_data,
    logged_arrays,
    runs_of,
    safe_stem,
    save_figure,
    write_table,
)
from pipeline.data.images import gamma_encode, write_exr

log = logging.getLogger(__name__)

COLOURS = {"dark": "tab:cyan", "bright": "tab:orange"}
TRUTH, REFERENCE = "analytic truth", "measured reference"
SCORED_AGAINST = "scored against"
BEYOND_GRID = "beyond grid"
# The metrics (render_<name>) that the tables score, by the start of their names.
_SCORED = ("rmse_", "hf_ratio_", "hf_rmse_", "flip", "ssim", "psnr_db")
# One reference render (and its distance from the truth) per pair of these cache keys.
_REFERENCE_KEYS = ("tags.cache.render_reference", "tags.cache.render_truth")


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
    return sorted(int(c[len(prefix) :]) for c in runs.columns if c.startswith(prefix))


def scored_against(runs: pd.DataFrame) -> pd.Series:
    """Per run, what its dataset's rows are scored against: :data:`TRUTH` where any run of
    the dataset logged truth metrics (``render_truth_rmse_dark``), else :data:`REFERENCE`."""
    truth = runs.get("metrics.render_truth_rmse_dark", pd.Series(np.nan, index=runs.index))
    has = truth.notna().groupby(runs["dataset"]).transform("any")
    return pd.Series(np.where(has, TRUTH, REFERENCE), index=runs.index)


def scored_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """Rendered runs with what the tables show: a :data:`SCORED_AGAINST` column and, for every
    logged ``render_<name>`` (``rmse_dark``, ``hf_ratio_bright_spp16``, ...), a
    ``metrics.scored_<name>``: the run's ``render_truth_<name>`` where its dataset is scored
    against the truth, else its ``render_<name>``.

    Datasets scored against the truth get one more row per reference render (per pair of
    reference and truth cache keys), model :data:`REFERENCE` (and the render settings in
    which reference renders of the dataset differ), whose scores are the reference's own
    ``render_reference_truth_<name>``; it sorts before every model.
    """
    runs = runs.copy()
    runs[SCORED_AGAINST] = against = scored_against(runs)
    scored = tuple(f"metrics.render_{name}" for name in _SCORED)
    names = [c[len("metrics.render_") :] for c in runs.columns if c.startswith(scored)]
    nothing = pd.Series(np.nan, index=runs.index)
    for name in names:
        truth = runs.get(f"metrics.render_truth_{name}", nothing)
        runs[f"metrics.scored_{name}"] = truth.where(
            against == TRUTH, runs[f"metrics.render_{name}"]
        )
    keyed = runs[against == TRUTH]
    if keyed.empty:
        return runs
    references = _reference_renders(keyed).copy()
    for name in names:
        references[f"metrics.scored_{name}"] = references.get(
            f"metrics.render_reference_truth_{name}", np.nan
        )
    references["model"] = REFERENCE + _render_differences(references)
    references["order"] = -np.inf
    return pd.concat([runs, references], ignore_index=True)


def _render_differences(references: pd.DataFrame) -> pd.Series:
    """``" [btf.render.lights=both]"``: the render settings in which a dataset's reference
    renders differ, per reference; ``""`` where a dataset has one."""
    settings = [c for c in references.columns if c.startswith("params.btf.render.")]
    suffix = pd.Series("", index=references.index)
    for _, group in references.groupby("dataset"):
        differ = [c for c in settings if group[c].astype(str).nunique() > 1]
        if differ:
            suffix[group.index] = [
                " [" + ", ".join(f"{c[len('params.') :]}={v}" for c, v in row.items()) + "]"
                for _, row in group[differ].astype(str).iterrows()
            ]
    return suffix


def beyond_grid_column(runs: pd.DataFrame, metric: str) -> pd.Series:
    """Per dataset, ``metrics.<metric>`` (a share beyond the grid) of its reference renders
    as a percentage: one value, or the range where renders differ; "–" where none logged."""

    def describe(values: pd.Series) -> str:
        values = values.dropna()
        if values.empty:
            return "–"
        low, high = 100 * values.min(), 100 * values.max()
        return f"{low:.1f} %" if np.isclose(low, high) else f"{low:.1f}–{high:.1f} %"

    column = f"metrics.{metric}"
    if column not in runs:
        return pd.Series("–", index=sorted(runs["dataset"].unique()), name=BEYOND_GRID)
    return _reference_renders(runs).groupby("dataset")[column].agg(describe).rename(BEYOND_GRID)


def _reference_renders(runs: pd.DataFrame) -> pd.DataFrame:
    """One run per reference render of each dataset (per pair of :data:`_REFERENCE_KEYS`)."""
    keys = [k for k in _REFERENCE_KEYS if k in runs] or ["run_id"]
    return runs.drop_duplicates(["dataset", *keys])


def _against(runs: pd.DataFrame) -> pd.Series:
    """:data:`SCORED_AGAINST` per dataset."""
    return runs.groupby("dataset")[SCORED_AGAINST].first()


def _target_words(bases) -> str:
    """What a table scores against, for its caption: "the analytic truth", "the measured
    reference", or both."""
    bases = set(bases)
    if bases == {TRUTH}:
        return f"the {TRUTH}"
    if bases == {REFERENCE}:
        return f"the {REFERENCE}"
    return f"the {TRUTH} or the {REFERENCE} (column '{SCORED_AGAINST}')"


def scoring_note(bases) -> str:
    """The sentences of a table's note that say what its rows are scored against."""
    bases = set(bases)
    parts = []
    if TRUTH in bases:
        parts.append(
            f"Rows scored against the {TRUTH}: each render is compared with the built-in "
            "material's generator rendered with the same scene, samples and seed, evaluated "
            "at every direction (no grid, no clamp); models are queried as they are (a neural "
            "decoder extrapolates beyond the measured grid's 75° ring, the measured BTF and "
            f"PCA clamp onto it). The column '{REFERENCE}' is the reference render's own "
            "distance from the truth: how far scoring against the reference is itself off."
        )
    if REFERENCE in bases:
        parts.append(
            f"Rows scored against the {REFERENCE}: each render is compared with the measured "
            "BTF's render (interpolated between its 81 × 81 directions), same scene, samples "
            "and seed; light and view directions beyond the grid's 75° ring are clamped onto "
            "it for every material alike, so the neural decoders' extrapolation is not "
            "scored."
        )
    parts.append(
        f"'{BEYOND_GRID}': the share of the (camera sample, light) pairs in the crop (Tables "
        "3-4) or on the lit cloth (cloth table), weighted by the light's irradiance, whose "
        "light or view direction lies beyond the measured grid, at the largest samples per "
        "pixel."
    )
    return " ".join(parts)


def table_crop(runs: pd.DataFrame, region: str) -> pd.DataFrame:
    """Table 3 (dark) or 4 (bright) of :func:`scored_runs`: per dataset (rows), what it is
    scored against, the crop's RMSE per model (columns, mean ± std over seeds) and the
    crop's share of samples beyond the grid."""
    table = tables.table_rmse(runs, f"scored_rmse_{region}")
    table.insert(0, SCORED_AGAINST, _against(runs).reindex(table.index))
    table[BEYOND_GRID] = (
        beyond_grid_column(runs, f"render_beyond_grid_share_{region}")
        .reindex(table.index)
        .fillna("–")
    )
    return table


def table_graininess(runs: pd.DataFrame) -> pd.DataFrame:
    """Rows (dataset, model, spp) of :func:`scored_runs`: both crops' RMSE, high-frequency
    energy ratio and (where logged) the RMSE of the high-pass parts against the row's
    target: the ratio alone cannot see fine detail in the wrong place."""
    target = {TRUTH: "truth", REFERENCE: "reference"}
    bases = set(runs[SCORED_AGAINST]) if SCORED_AGAINST in runs else {REFERENCE}
    word = target[bases.pop()] if len(bases) == 1 else "target"
    rows = []
    for spp in spp_levels(runs):
        for (dataset, model), group in runs.groupby(["dataset", "model"], sort=False):
            row = {
                "dataset": dataset,
                SCORED_AGAINST: group[SCORED_AGAINST].iloc[0],
                "model": model,
                "spp": spp,
            }
            for region in REGIONS:
                rmse = group.get(f"metrics.scored_rmse_{region}_spp{spp}")
                hf = group.get(f"metrics.scored_hf_ratio_{region}_spp{spp}")
                hf_rmse = group.get(f"metrics.scored_hf_rmse_{region}_spp{spp}")
                if rmse is None or hf is None:
                    continue
                row[f"{region}: RMSE"] = tables.mean_std(rmse)
                row[f"{region}: HF energy / {word}"] = tables.mean_std(hf)
                if hf_rmse is not None and hf_rmse.notna().any():  # not logged by every render
                    row[f"{region}: HF RMSE"] = tables.mean_std(hf_rmse)
            rows.append(row)
    if not rows:
        return pd.DataFrame()
    order = {m: i for i, m in enumerate(tables.model_columns(runs))}
    table = pd.DataFrame(rows)
    return table.sort_values(
        ["dataset", "spp", "model"], key=lambda s: s.map(order) if s.name == "model" else s
    )


def table_cloth(runs: pd.DataFrame, metric: str = "rmse_cloth") -> pd.DataFrame:
    """Rows (dataset, spp) x model columns of :func:`scored_runs`: ``metric`` (by default the
    RMSE over every pixel wholly on lit cloth; a larger sample than the crops, so a steadier
    ranking), mean ± std over seeds. With what it is scored against and the lit cloth's
    share beyond the grid."""
    parts = [
        tables.table_rmse(runs, f"scored_{metric}_spp{spp}").assign(spp=spp)
        for spp in spp_levels(runs)
        if f"metrics.scored_{metric}_spp{spp}" in runs
    ]
    if not parts:
        return pd.DataFrame()
    table = pd.concat(parts).reset_index().fillna("–")  # a model not rendered at that spp
    table[SCORED_AGAINST] = table["dataset"].map(_against(runs))
    table[BEYOND_GRID] = (
        table["dataset"].map(beyond_grid_column(runs, "render_beyond_grid_share")).fillna("–")
    )
    first = ["dataset", SCORED_AGAINST, "spp"]
    return table[[*first, *[c for c in table.columns if c not in first]]]


def sections(runs: pd.DataFrame, out: Path, settings=None) -> list[str]:
    """Tables 3-4, the lit-cloth RMSE and the graininess per spp, and Fig. 8 (when the
    cache is at hand), from MLflow's runs of every method; nothing when no run rendered.
    Runs pool as seeds only when their recipe and render settings match
    (``label_runs(render=True)``)."""
    runs = runs_of(runs, RENDERED)
    if runs.empty or "metrics.render_rmse_dark" not in runs:
        return []
    runs = rendered_runs(
        tables.label_runs(runs[runs["metrics.render_rmse_dark"].notna()], render=True)
    )
    if runs.empty:
        return []
    scored = scored_runs(runs)
    bases = set(scored[SCORED_AGAINST])
    against = _target_words(bases)
    note = (
        "RMSE of linear radiance (the key light gives irradiance 1 at the sheet's centre, "
        "so values are in the BTF's units); mean ± std over seeds (n), at "
        f"{spp_levels(runs)[-1]} samples per pixel. The crops (marked in Fig. 8) are "
        f"chosen on the render they are scored against. {scoring_note(bases)}"
    )
    found = [
        write_table(
            table_crop(scored, region),
            out,
            f"table{number}_render_{region}",
            f"Table {number}: RMSE of the rendered {region} crop against {against}",
            note,
        )
        for number, region in ((3, "dark"), (4, "bright"))
    ]
    frame_note = (
        "The frame as displayed (exposure, gamma 2.2, clipped to [0, 1]: the PNG's "
        "values), compared with the render it is scored against by "
        "pipeline.core.image_metrics (FLIP: NVIDIA's flip-evaluator at 67 pixels per "
        "degree; SSIM: Gaussian window, sigma 1.5). LPIPS needs network weights from "
        f"a hub that cannot be fetched here and is not reported. {scoring_note(bases)}"
    )
    optional = [
        (
            "render_cloth",
            table_cloth(scored),
            f"RMSE of the render over the whole lit cloth against {against}",
            "As Tables 3-4, over every pixel whose camera samples all land on cloth that a "
            "light sees (no silhouette, shadow or floor pixels), at each samples-per-pixel "
            f"level. {scoring_note(bases)}",
        ),
        (
            "render_flip",
            table_cloth(scored, "flip"),
            "LDR-FLIP (mean; 0 is identical, lower is better) of the whole frame against "
            f"{against}",
            frame_note,
        ),
        (
            "render_ssim",
            table_cloth(scored, "ssim"),
            f"SSIM (1 is identical) of the whole frame against {against}",
            frame_note,
        ),
        (
            "render_graininess",
            table_graininess(scored),
            f"Does the graininess survive rendering? Scored against {against}",
            "Each crop at every samples-per-pixel level: RMSE and the high-frequency energy "
            "(image minus its Gaussian blur, sigma 1 pixel) of the crop over the target's "
            "(the render it is scored against): above 1 the model adds grain, near 1 it has "
            "the target's texture, below 1 it is smoother. Pixel samples are shared with the "
            f"target, so what differs is the BTF alone. {scoring_note(bases)}",
        ),
    ]
    for stem, table, title, text in optional:
        if not table.empty:
            found.append(write_table(table, out, stem, title, text))
    files = draw_fig8(runs, out)
    if files:
        found.append(
            "## Fig. 8: renders\n\n"
            + "\n".join(f"![{p.stem}]({p.name})" for p in files if p.suffix == ".png")
            + "\n"
        )
    return found


def logged_renders(run_id: str) -> dict[str, np.ndarray] | None:
    """The Fig. 8 data a run logged (``render/fig8_data.npz``:
    :func:`pipeline.btf.render.stage.fig8_data`), or None."""
    from pipeline.btf.render.stage import FIG8_DATA

    return logged_arrays(run_id, f"render/{FIG8_DATA}")


def draw_fig8(runs: pd.DataFrame, out: Path, data_of=logged_renders) -> list[Path]:
    """One figure per dataset (the lowest seed's renders at the largest spp: the truth when
    the runs have one, the reference, then each model): PNG, and an EXR of each render;
    returns the written files. Images are what the runs logged (``data_of``: run id -> its
    :func:`~pipeline.btf.render.stage.fig8_data`), the truth and reference the first
    model's; a dataset none of whose runs logged them is skipped with a warning."""
    for stale in out.glob("fig8_*"):
        stale.unlink()
    written = []
    for dataset, group in runs.groupby("dataset"):
        group = group.sort_values(["order", "seed"])
        logged = first_with_data(group, data_of, f"Fig. 8 of {dataset}", log)
        if not logged:
            log.warning("Fig. 8 of %s: none of its runs logged its renders", dataset)
            continue
        first = logged[0][1]
        # (label, the data holding it, its name there): the truth and reference once.
        own = ["truth", "reference"] if "truth_image" in first else ["reference"]
        entries = [(name, first, name) for name in own]
        entries += [(model, data, "model") for model, data in logged]
        levels = [int(s) for s in first["spp"]]
        crops = {
            region: tuple(int(v) for v in first["crops"][i]) for i, region in enumerate(REGIONS)
        }
        size = int(float(group["params.btf.render.crop_size"].iloc[0]))
        spp = levels[-1]
        panels = [(label, data[f"{name}_image"]) for label, data, name in entries]
        by_spp = {
            s: [(label, data[f"{name}_crops"][i]) for label, data, name in entries]
            for i, s in enumerate(levels)
        }
        stem = "fig8_" + safe_stem(dataset)
        exposure = float(group["params.btf.render.exposure"].iloc[0])
        seed = int(group["seed"].min())
        title = f"{dataset}, {spp} spp, seed {seed}"
        written.append(_grid(panels, crops, size, exposure, title, out / f"{stem}.png"))
        crops_path = out / f"{stem}_crops_per_spp.png"
        written.append(_crops_per_spp(by_spp, f"{dataset}, seed {seed}", crops_path))
        for name, image in panels:
            path = out / f"{stem}_{safe_stem(name)}.exr"
            write_exr(path, image)
            written.append(path)
    return written


def _grid(panels, crops: dict, size: int, exposure: float, title: str, path: Path) -> Path:
    """Renders in a row, both crops marked, each crop enlarged below its render."""
    columns = len(panels)
    fig = Figure(figsize=(2.4 * columns, 2.4 * 2 + 0.4))
    axes = fig.subplots(3, columns, squeeze=False, gridspec_kw={"height_ratios": [2, 1, 1]})
    for column, (name, image) in enumerate(panels):
        shown = gamma_encode(image * np.float32(exposure))
        axes[0, column].imshow(shown, interpolation="nearest")
        axes[0, column].set_title(name, fontsize=9)
        for row, region in enumerate(REGIONS, start=1):
            r, c = crops[region]
            corner = (c - 0.5, r - 0.5)
            outline = Rectangle(corner, size, size, fill=False, edgecolor=COLOURS[region], lw=1.2)
            axes[0, column].add_patch(outline)
            axes[row, column].imshow(shown[r : r + size, c : c + size], interpolation="nearest")
            axes[row, column].set_ylabel(
                region if column == 0 else "", fontsize=8, color=COLOURS[region]
            )
    for axis in axes.ravel():
        axis.set_xticks([])
        axis.set_yticks([])
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    return path


def _crops_per_spp(by_spp: dict, title: str, path: Path) -> Path:
    """Both crops of every render at every spp, side by side: one row per (region, spp),
    one column per render, to see whether a model's grain outlives the pixel's samples.
    ``by_spp``: spp -> [(render, its crops (regions, size, size, 3))]. Each region is
    exposed so that the first render's crop (the truth, else the reference) at the largest
    spp has its 99th percentile at white (the dark crop would be black at the frame's
    exposure); a row's renders share it."""
    levels = sorted(by_spp)
    columns = len(by_spp[levels[-1]])
    fig = Figure(figsize=(1.6 * columns + 0.6, 1.6 * 2 * len(levels) + 0.4))
    axes = fig.subplots(2 * len(levels), columns, squeeze=False)
    for block, region in enumerate(REGIONS):
        reference = by_spp[levels[-1]][0][1][block]
        exposure = 1.0 / max(float(np.percentile(reference, 99)), 1e-6)
        for offset, spp in enumerate(levels):
            row = block * len(levels) + offset
            for column, (name, crops) in enumerate(by_spp[spp]):
                shown = gamma_encode(crops[block] * np.float32(exposure))
                axes[row, column].imshow(np.clip(shown, 0, 1), interpolation="nearest")
                if row == 0:
                    axes[row, column].set_title(name, fontsize=8)
            axes[row, 0].set_ylabel(f"{region}, {spp} spp", fontsize=8, color=COLOURS[region])
    for axis in axes.ravel():
        axis.set_xticks([])
        axis.set_yticks([])
    fig.suptitle(f"{title}\nthe crops at each samples-per-pixel level", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return path
