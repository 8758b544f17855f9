"""The command lines of the README, run as a user runs them: each in a process of its own
(``helpers.pipeline_command``)."""

import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT, WIRING_STEPS, pipeline_command
from mlflow.tracking import MlflowClient

from pipeline.core.store import tracking_uri


@pytest.mark.slow
def test_joblib_sweep_gives_one_parent_and_reuses_the_pca(tmp_path, mlflow_template):
    runs = tmp_path / "runs"
    mlflow_template(runs)
    # A new interpreter, as a user's: joblib's workers are processes of their own.
    done = subprocess.run(
        [sys.executable, "-m", "pipeline", "-m", "experiment=smoke", "model.k=4,8", "seed=1"]
        + ["hydra/launcher=joblib", f"paths.runs={runs}", f"train.max_steps={WIRING_STEPS}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )

    assert done.returncode == 0, done.stderr[-3000:]

    client = MlflowClient(tracking_uri(runs))
    experiment = client.get_experiment_by_name("smoke")
    all_runs = client.search_runs([experiment.experiment_id])
    parents = [r for r in all_runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in all_runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert len(children) == 2
    assert {r.data.tags["mlflow.parentRunId"] for r in children} == {parents[0].info.run_id}
    assert {r.info.status for r in children} == {"FINISHED"}
    assert {(r.data.params["model.k"], r.data.params["seed"]) for r in children} == {
        ("4", "1"),
        ("8", "1"),
    }
    # One PCA for the whole sweep: computed once, a hit in every other job's log.
    logs = [p.read_text() for p in (runs / "hydra" / "multirun").glob("*/*/*.log")]
    pca_lines = [line for text in logs for line in text.splitlines() if "stage pca" in line]
    assert len(pca_lines) == 2
    assert sum("computed" in line for line in pca_lines) == 1
    assert len({r.data.tags["cache.pca"] for r in children}) == 1

    # The UI shows the work: the sweep's parent names what it swept; each job holds its
    # resolved config, its overrides, its log and a description; the experiment opens
    # on its runs (not on MLflow's GenAI overview).
    assert parents[0].data.params["model.k"] == "4,8"
    # ... and carries a description and each job's headline metrics (names made legal).
    assert "Hydra sweep" in parents[0].data.tags["mlflow.note.content"]
    for child in children:
        job = child.info.run_name.replace("=", "_")
        assert parents[0].data.metrics[f"{job}/rmse"] == child.data.metrics["rmse"]
    # The parent names its process, so that a later start ends it if the sweep was killed.
    assert parents[0].data.tags["pid"].isdigit() and parents[0].data.tags["host"]
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"
    child = children[0]
    assert "rmse_mean_abrdf" in child.data.tags["mlflow.note.content"]
    assert f"model.k={child.data.params['model.k']}" in child.data.tags["overrides"].split()
    paths = _artifact_paths(client, child.info.run_id)
    assert {
        "config/resolved.yaml",
        "config/overrides.yaml",
        "hydra/config.yaml",
        "hydra/overrides.yaml",
        "hydra/__main__.log",
    } <= paths, paths
    assert any(p.startswith("figures/fig7_") and p.endswith(".png") for p in paths), paths
    resolved = client.download_artifacts(child.info.run_id, "config/resolved.yaml", str(tmp_path))
    assert f"k: {child.data.params['model.k']}" in Path(resolved).read_text()


def _artifact_paths(client, run_id, path=None):
    found = set()
    for item in client.list_artifacts(run_id, path):
        found |= _artifact_paths(client, run_id, item.path) if item.is_dir else {item.path}
    return found


def test_bad_input_exits_non_zero_with_the_path(tmp_path):
    missing = tmp_path / "nowhere"
    done = pipeline_command(
        "experiment=smoke",
        f"paths.runs={tmp_path / 'runs'}",
        "dataset=ubo2003",
        f"dataset.root={missing}",
    )
    assert done.returncode != 0
    assert str(missing) in done.stderr


# ------------------------------------------------------------- python -m pipeline.cache


def _one_entry(cache_dir: Path) -> None:
    import numpy as np

    from pipeline.core.cache import StageCache, save_arrays

    StageCache(cache_dir).run("load", "1", {}, {}, lambda folder: save_arrays(folder, x=np.ones(2)))


def test_the_cache_command_takes_key_value_settings_like_the_jobs(tmp_path, capsys):
    from pipeline.cache import main

    _one_entry(tmp_path / "runs" / "cache")
    _one_entry(tmp_path / "elsewhere")
    assert main(["ls", f"paths.runs={tmp_path / 'runs'}"]) == 0
    assert f"cache {tmp_path / 'runs' / 'cache'}" in capsys.readouterr().out
    # paths.cache wins over <paths.runs>/cache.
    assert (
        main(
            [
                "ls",
                f"paths.cache={tmp_path / 'elsewhere'}",
                "entries=false",
                f"paths.runs={tmp_path / 'runs'}",
            ]
        )
        == 0
    )
    assert f"cache {tmp_path / 'elsewhere'}" in capsys.readouterr().out
    assert main(["verify", f"paths.cache={tmp_path / 'elsewhere'}", "fix=true"]) == 0
    assert "0 damaged" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, said",
    [
        (
            ["ls", "paths.run=x"],
            "'paths.run=x' is not a setting of the ls command (did you mean paths.runs?)",
        ),
        (
            ["gc", "dry-run=true"],
            "'dry-run=true' is not a setting of the gc command (did you mean dry_run?)",
        ),
        (["lss"], "unknown command 'lss' (did you mean ls?)"),
        (["ls", "fix=true"], "fix is a setting of verify, not of ls"),
        (["ls", "entries=maybe"], "entries='maybe' must be one of True, False"),
        (["ls", "paths.runs="], "paths.runs=None must be a non-empty string"),
        (["ls", "paths.runs=a", "paths.runs=b"], "paths.runs is given twice"),
        (["paths.runs=a", "ls"], "no command: give one of ls, verify, gc first"),
        (
            ["gc", "--dry-run"],
            "'--dry-run' is not a setting of the gc command (did you mean dry_run?)",
        ),
        (["ls", "gc"], "'gc' is not a setting of the ls command"),
    ],
)
def test_the_cache_command_refuses_a_bad_word_naming_it(argv, said, capsys):
    from pipeline.cache import main

    with pytest.raises(SystemExit) as exit:
        main(argv)
    assert exit.value.code == 2
    assert said in capsys.readouterr().err


def test_the_cache_command_answers_a_bad_setting_before_importing_mlflow(tmp_path):
    """A typo is answered before MLflow, torch, Hydra or pandas is imported (seconds each),
    and ``--help`` lists every setting."""
    probe = (
        "import sys\nfrom pipeline.cache import main\ntry:\n    main(['gc', 'bogus=1'])\n"
        "except SystemExit as exit:\n    code = exit.code\n"
        "print(sorted(m for m in ('mlflow', 'torch', 'hydra', 'pandas') if m in sys.modules))\n"
        "sys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2
    assert "'bogus=1' is not a setting of the gc command" in done.stderr
    assert done.stdout.strip() == "[]"
    helped = pipeline_command("--help", module="pipeline.cache", cwd=tmp_path)
    assert helped.returncode == 0
    for key in ("paths.runs=", "paths.cache=", "entries=", "fix=", "dry_run="):
        assert key in helped.stdout
