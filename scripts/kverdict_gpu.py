"""Table 2 and the k verdict from the JSON lines of ``scripts/gpu_convergence.py``: per
material, peak learning rate and length, each model's final RMSE as mean ± std over seeds,
the blocked k verdict of :mod:`pipeline.btf.k_verdict` over the seeds run at every k, the
runs whose curve jumped, and the curves drawn one panel per material and learning rate.

    python scripts/kverdict_gpu.py docs/measurements/gpu_kverdict_2026-11-27.jsonl \
        docs/measurements/gpu_lr_2026-11-27.jsonl --figure docs/figures/kverdict_gpu.png

A run is *diverged* when its final RMSE is more than ``DIVERGED`` times the lowest point of
its own curve (it did not recover from a jump): it is shown, and left out of the means and
the verdict. A *jump* is a curve point more than ``JUMP`` times the point before it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from pipeline.btf.k_verdict import blocked_verdict, describe
from pipeline.btf.tables import mean_std

DIVERGED = 2.0
JUMP = 2.0


def load(paths: list[str]) -> pd.DataFrame:
    """One row per trained Neural BTF or clustered model of the files that has a curve (the
    latent texture's lines and older lines without one are left out), with its label, jumps
    and divergence."""
    lines = [
        json.loads(text)
        for path in paths
        for text in Path(path).read_text().splitlines()
        if text.strip()
    ]
    rows = [r for r in lines if r.get("model") in ("neural_btf", "clustered") and r.get("curve")]
    if not rows:
        raise SystemExit(
            f"kverdict_gpu.py: no Neural BTF or clustered line with a curve in {paths}"
        )
    runs = pd.DataFrame(rows)
    runs["lr"] = runs.get("lr", pd.Series(0.002, index=runs.index)).fillna(0.002)
    k = runs.get("k", pd.Series(np.nan, index=runs.index))
    runs["label"] = [
        "Neural BTF" if m == "neural_btf" else f"k = {int(v)}"
        for m, v in zip(runs["model"], k, strict=True)
    ]
    runs["jumps"] = [
        sum(b[1] > JUMP * a[1] for a, b in zip(c, c[1:], strict=False)) for c in runs["curve"]
    ]
    runs["diverged"] = [
        r > DIVERGED * min(p[1] for p in c)
        for r, c in zip(runs["rmse"], runs["curve"], strict=True)
    ]
    return runs


def order(label: str) -> tuple[int, int]:
    """Neural BTF first, then the clustered models by k."""
    return (0, 0) if label == "Neural BTF" else (1, int(label.split()[-1]))


def report(runs: pd.DataFrame) -> str:
    """The Markdown tables of every (material, lr, steps) group of runs."""
    parts = []
    for (material, lr, steps), group in runs.groupby(["material", "lr", "steps"]):
        kept = group[~group["diverged"]]
        labels = sorted(group["label"].unique(), key=order)
        row = {label: mean_std(kept.loc[kept["label"] == label, "rmse"]) for label in labels}
        row["runs with a jump (> 2 x)"] = f"{int((group['jumps'] > 0).sum())} of {len(group)}"
        gone = group[group["diverged"]]
        row["diverged (left out)"] = (
            ", ".join(f"{r.label} seed {r.seed} ({r.rmse:.4f})" for r in gone.itertuples())
            or "none"
        )
        parts.append(
            f"**{material}, peak lr {lr:g}, {steps} steps** (RMSE, mean ± std over seeds)\n\n"
            + pd.DataFrame([row]).to_markdown(index=False)
        )
        clustered = kept[kept["model"] == "clustered"]
        if clustered.empty:
            continue
        blocks = clustered.pivot_table(index="seed", columns="k", values="rmse").dropna()
        if blocks.shape[0] >= 2 and blocks.shape[1] >= 2:
            verdict = describe(blocked_verdict(blocks))
            parts.append(
                "k verdict\n\n"
                + pd.Series(
                    {key.replace("|", "\\|"): value for key, value in verdict.items()}, name=""
                ).to_markdown()
            )
    return "\n\n".join(parts)


def figure(runs: pd.DataFrame, path: str) -> None:
    """RMSE against steps: one panel per (material, lr), a colour per model, a style per seed."""
    panels = list(runs.groupby(["material", "lr"]))
    labels = sorted(runs["label"].unique(), key=order)
    colours = {label: f"C{i}" for i, label in enumerate(labels)}
    fig = Figure(figsize=(5 * len(panels), 4))
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharey=True))
    for ax, ((material, lr), group) in zip(axes, panels, strict=True):
        for r in sorted(group.itertuples(), key=lambda r: (order(r.label), r.seed)):
            steps, rmse = np.array(r.curve).T
            label = r.label if r.seed == group["seed"].min() else None
            ax.plot(
                steps,
                rmse,
                ("-", "--", ":")[r.seed % 3],
                color=colours[r.label],
                lw=0.8,
                label=label,
            )
        ax.set_title(f"{material}, peak lr {lr:g} ({group['gpu'].iloc[0] or 'CPU'})", fontsize=9)
        ax.set_xlabel("training step")
        ax.set_yscale("log")
        ax.set_ylim(0.006, 0.2)
        ax.legend(fontsize=7, title="line style: seed 0 / 1 / 2", title_fontsize=7)
    axes[0].set_ylabel("RMSE of 256 fixed texels, all directions")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("lines", nargs="+", help="JSON-lines files of scripts/gpu_convergence.py")
    parser.add_argument("--figure", default=None, help="PNG of the curves")
    args = parser.parse_args()
    runs = load(args.lines)
    print(report(runs))
    if args.figure:
        figure(runs, args.figure)


if __name__ == "__main__":
    main()
