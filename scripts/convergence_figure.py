"""RMSE against training steps for the runs of ``experiment=convergence``: Neural BTF's
``curve_rmse`` (eq. 10 on 256 fixed texels at every direction, logged every 500 steps) and
the latent texture's training-batch RMSE (the square root of its loss, from its train
stage's ``losses.json``), each run's final eq. 10 RMSE over the whole crop as a marker;
one panel per material. Prints each run's final RMSE and the change from 1x to 2x.

    python scripts/convergence_figure.py /work/conv_runs docs/figures/convergence.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from mlflow.tracking import MlflowClient

from pipeline.core.store import tracking_uri


def main(runs_dir: str, figure: str) -> None:
    client = MlflowClient(tracking_uri(runs_dir))
    experiment = client.get_experiment_by_name("convergence")
    runs = [
        r
        for r in client.search_runs([experiment.experiment_id])
        if r.info.status == "FINISHED" and r.data.params.get("model.name") not in (None, "pca")
    ]
    materials = sorted({r.data.params["dataset.synthetic.material"] for r in runs})
    fig = Figure(figsize=(5.5 * len(materials), 4))
    axes = np.atleast_1d(fig.subplots(1, len(materials)))
    finals = {}
    for ax, material in zip(axes, materials, strict=True):
        for run in sorted(runs, key=lambda r: r.info.start_time):
            params = run.data.params
            if params["dataset.synthetic.material"] != material:
                continue
            name = params["model.name"]
            steps = int(run.data.metrics.get("train_steps", 0))
            label = f"{name}, {steps} steps"
            if name == "latent_texture":
                folder = Path(params["paths.cache"]) / "train_latent_texture"
                entry = folder / run.data.tags["cache.train_latent_texture"]
                losses = json.loads((entry / "losses.json").read_text())
                x = np.linspace(steps / len(losses), steps, len(losses))
                ax.plot(x, np.sqrt(losses), lw=1, label=f"{label} (batch RMSE)")
            else:
                history = client.get_metric_history(run.info.run_id, "curve_rmse")
                if history:
                    ax.plot(
                        [m.step for m in history],
                        [m.value for m in history],
                        lw=1,
                        label=f"{label} (curve)",
                    )
            rmse = run.data.metrics["rmse"]
            ax.plot([steps], [rmse], "o", ms=5)
            finals.setdefault((material, name), []).append((steps, rmse))
        ax.set_title(material)
        ax.set_xlabel("training step")
        ax.set_ylabel("RMSE (normalised)")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(figure, dpi=110)
    for (material, name), points in sorted(finals.items()):
        points.sort()
        # Each doubling's change (the criterion compares a run with the one twice as long).
        changes = [
            f"{a} -> {b} steps {100 * (rb / ra - 1):+.1f} %"
            for (a, ra), (b, rb) in zip(points, points[1:], strict=False)
        ]
        listed = ", ".join(f"{s} steps {r:.5f}" for s, r in points)
        print(f"{material} {name}: {listed}" + (f"; {', '.join(changes)}" if changes else ""))


if __name__ == "__main__":
    main(*sys.argv[1:3])
