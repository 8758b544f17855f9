"""scripts/convergence_figure.py on the JSON lines of scripts/gpu_convergence.py: the
figure is drawn and each doubling's change is printed per seed, computed from the lines."""

import json
import runpy
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _line(model: str, steps: int, seed: int, rmse: float) -> dict:
    curve = [[0, 0.2], [steps // 2, 2 * rmse], [steps, rmse]]
    return {
        "material": "corduroy",
        "model": model,
        "multiple": steps / 100,
        "seed": seed,
        "steps": steps,
        "rmse": rmse,
        "device": "cpu",
        "gpu": None,
        "curve": curve,
    }


def test_the_figure_and_each_doublings_change_per_seed(tmp_path, capsys, monkeypatch):
    lines = [
        _line("neural_btf", 100, 0, 0.020),
        _line("neural_btf", 200, 0, 0.015),
        _line("neural_btf", 100, 1, 0.030),
        _line("clustered", 100, 0, 0.040),
    ]
    source = tmp_path / "lines.jsonl"
    source.write_text("".join(json.dumps(line) + "\n" for line in lines))
    figure = tmp_path / "figure.png"
    monkeypatch.setattr(sys, "argv", ["convergence_figure.py", str(source), str(figure)])
    runpy.run_path(str(ROOT / "scripts" / "convergence_figure.py"), run_name="__main__")
    printed = capsys.readouterr().out.splitlines()
    assert figure.stat().st_size > 0
    assert (
        "corduroy neural_btf 0: 100 steps 0.02000, 200 steps 0.01500; "
        "100 -> 200 steps -25.0 %" in printed
    )
    assert "corduroy neural_btf 1: 100 steps 0.03000" in printed
    assert "corduroy clustered 0: 100 steps 0.04000" in printed
