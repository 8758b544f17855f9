"""RMSE against training steps for the runs of ``experiment=convergence``: Neural BTF's
``curve_rmse`` (eq. 10 on 256 fixed texels at every direction, logged every 500 steps) and
the latent texture's training-batch RMSE (the square root of its loss, from its train
stage's ``losses.json``), each run's final eq. 10 RMSE over the whole crop as a marker;
one panel per material. Prints each run's final RMSE and the change from 1x to 2x.

    python scripts/convergence_figure.py /work/conv_runs docs/figures/convergence.png

Given the JSON lines of ``scripts/gpu_convergence.py`` instead of a runs folder, it draws
their curves (any model with one: one colour per length, one line style per seed) and prints the
same changes, per seed:

    python scripts/convergence_figure.py docs/measurements/gpu_convergence_2026-11-27.jsonl \
        docs/figures/convergence_gpu.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from mlflow.tracking import MlflowClient

from pipeline.core.store import tracking_uri


def from_lines(path: str, figure: str) -> None:
    """The curves and final RMSEs of ``scripts/gpu_convergence.py``'s output."""
    lines = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    materials = sorted({line["material"] for line in lines})
    multiples = sorted({line["multiple"] for line in lines})
    colours = {multiple: f"C{i}" for i, multiple in enumerate(multiples)}
    fig = Figure(figsize=(5.5 * len(materials), 4))
    axes = np.atleast_1d(fig.subplots(1, len(materials)))
    for ax, material in zip(axes, materials, strict=True):
        for line in sorted(lines, key=lambda x: (x["multiple"], x["seed"])):
            if line["material"] != material or not line.get("curve"):
                continue
            steps, rmse = np.array(line["curve"]).T
            style = ("-", "--", ":")[line["seed"] % 3]
            colour = colours[line["multiple"]]
            label = f"{line['model']}, {line['steps']} steps, seed {line['seed']}"
            ax.plot(steps, rmse, style, color=colour, lw=1, label=label)
            ax.plot([line["steps"]], [line["rmse"]], "o", color=colour, ms=4)
        ax.set_title(f"{material} ({lines[0].get('gpu') or lines[0]['device']})")
        ax.set_xlabel("training step")
        ax.set_ylabel("RMSE (normalised)")
        ax.set_yscale("log")
        ax.set_ylim(0.008, 0.2)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(figure, dpi=110)
    finals: dict = {}
    for line in lines:
        key = (line["material"], line["model"], line["seed"])
        finals.setdefault(key, []).append((line["steps"], line["rmse"]))
    report(finals)


def report(finals: dict) -> None:
    """Each run's final RMSE and each doubling's change, one line per group."""
    for key, points in sorted(finals.items()):
        points.sort()
        # Each doubling's change (the criterion compares a run with the one twice as long).
        changes = [
            f"{a} -> {b} steps {100 * (rb / ra - 1):+.1f} %"
            for (a, ra), (b, rb) in zip(points, points[1:], strict=False)
        ]
        listed = ", ".join(f"{s} steps {r:.5f}" for s, r in points)
        name = " ".join(str(part) for part in key)
        print(f"{name}: {listed}" + (f"; {', '.join(changes)}" if changes else ""))


def main(runs_dir: str, figure: str) -> None:
    if runs_dir.endswith(".jsonl"):
        return from_lines(runs_dir, figure)
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
                # Stores written before the latent texture's stage was named "train" tag
                # it "train_latent_texture" (the runs of docs/results.md's CPU table).
                tags = run.data.tags
                stage = "train" if "cache.train" in tags else "train_latent_texture"
                entry = Path(params["paths.cache"]) / stage / tags[f"cache.{stage}"]
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
    report(finals)


if __name__ == "__main__":
    main(*sys.argv[1:3])
