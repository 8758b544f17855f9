"""The RMSE-versus-time curves of training (``train.curve_every``), from MLflow.

Each point is the eq. 10 RMSE of a fixed subsample of texels at every training direction
(``curve_rmse``) against the training seconds so far (``curve_seconds``), logged by the
train stage at the same step. Runs of one model trained for different lengths share the
start of their curve (the learning-rate schedule does not depend on the length), so the
plot shows directly what a longer run would gain.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from pipeline.core.report import save_figure, write_file


def curve_points(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per curve point of every run that logged a curve."""
    from mlflow.tracking import MlflowClient

    if "metrics.curve_rmse" not in runs:
        return pd.DataFrame()
    client = MlflowClient()
    rows = []
    for _, run in runs[runs["metrics.curve_rmse"].notna()].iterrows():
        seconds = {m.step: m.value for m in client.get_metric_history(run.run_id, "curve_seconds")}
        epochs = run.get("params.train.epochs", "?")
        for m in client.get_metric_history(run.run_id, "curve_rmse"):
            rows.append(
                {
                    "dataset": run["dataset"],
                    "model": run["model"],
                    "order": run["order"],
                    "length": run["epochs"],  # numeric, for sorting: "100" < "24"
                    "base_model": run["base_model"],
                    "epochs": epochs,
                    "seed": run["seed"],
                    "run_id": run.run_id,
                    "step": m.step,
                    "seconds": seconds.get(m.step),
                    "rmse": m.value,
                }
            )
    points = pd.DataFrame(rows).sort_values(["dataset", "order", "length", "run_id", "step"])
    return points.drop(columns=["order", "length"])


def curves_section(runs: pd.DataFrame, out: Path, tolerance: float = 0.05) -> str:
    """Plot the curves (one figure per dataset), write their points; return the section.

    Where a model was trained for several lengths, a dotted line marks ``tolerance`` above
    the end of its longest curve: a shorter run ending under it is converged."""
    points = curve_points(runs)
    if points.empty:
        return ""
    write_file(out / "training_curves.csv", points.to_csv(index=False))
    lines = [
        "## Training: RMSE versus time\n",
        "Points: `training_curves.csv`. RMSE of a fixed subsample of texels at every "
        "training direction; time = training seconds (measuring excluded).\n",
    ]
    for i, (dataset, group) in enumerate(points.groupby("dataset")):
        fig = Figure(figsize=(6, 4))
        ax = fig.subplots()
        runs_in_order = group.groupby(["model", "epochs", "run_id"], sort=False)
        colours = {}
        for (model, epochs, run_id), curve in runs_in_order:
            label = model if model.endswith("epochs)") else f"{model} ({epochs} epochs)"
            (line,) = ax.plot(curve["seconds"] / 60, curve["rmse"], marker=".", label=label)
            colours[run_id] = line.get_color()
        for base, runs_of_model in group.groupby("base_model", sort=False):
            lengths = pd.to_numeric(runs_of_model["epochs"], errors="coerce")
            if lengths.nunique() < 2:
                continue
            longest = runs_of_model[lengths == lengths.max()]
            end = longest.iloc[-1]
            ax.axhline(
                end["rmse"] * (1 + tolerance),
                color=colours[end["run_id"]],
                ls=":",
                lw=1,
                label=f"{base}: {end['epochs']}-epoch end + {tolerance:.0%}",
            )
        ax.set_xlabel("training time [min]")
        ax.set_ylabel("RMSE (normalized)")
        ax.set_yscale("log")
        ax.set_title(dataset, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"training_curves_{i}.png"
        save_figure(fig, out / name)
        last = runs_in_order.tail(1)
        summary = last[["model", "epochs", "seconds", "rmse"]].rename(
            columns={"seconds": "training [s]", "rmse": "last curve RMSE"}
        )
        lines.append(
            f"### {dataset}\n\n![curves]({name})\n\n"
            f"{summary.to_markdown(index=False, floatfmt='.4g')}\n"
        )
    return "\n".join(lines)
