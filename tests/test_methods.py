"""The method registry (pipeline.core.methods): the job and the tables command know a method
only through its config file, so a method added by config alone runs and reports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from helpers import CONF_DIR, ROOT, pipeline_command
from mlflow.tracking import MlflowClient

from pipeline.core.errors import ConfigError
from pipeline.core.methods import Method, method_of, registered, reports
from pipeline.core.store import NOTE_TAG, tracking_uri

# A method that lives outside the package: the job must find it through its YAML only.
DUMMY_MODULE = """
from pipeline.core.methods import Method

def run(ctx):
    return {"rmse": 0.25 * ctx.cfg.method.scale, "extra": 1.0}

def sections(runs, out, settings):
    (out / "dummy.md").write_text(f"{len(runs)} runs")
    return [f"## Dummy\\n\\n{len(runs)} runs of {sorted(set(runs['params.method.name']))}\\n"]

DUMMY = Method(name="dummy", paper="Z", run=run, description="**A dummy method**",
               headline=("rmse",), reports=("dummy_method",))
"""
DUMMY_YAML = "name: dummy\nspec: dummy_method:DUMMY\nscale: 2.0\n"


@pytest.fixture
def dummy_conf(tmp_path: Path) -> Path:
    """A config folder with only ``method/dummy.yaml``, and the dummy's module beside it."""
    (tmp_path / "code").mkdir()
    (tmp_path / "code" / "dummy_method.py").write_text(DUMMY_MODULE)
    (tmp_path / "conf" / "method").mkdir(parents=True)
    (tmp_path / "conf" / "method" / "dummy.yaml").write_text(DUMMY_YAML)
    return tmp_path


def test_a_method_added_by_config_alone_runs_and_reports(dummy_conf, tmp_path):
    runs = tmp_path / "runs"
    env = {"PYTHONPATH": str(dummy_conf / "code"), "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline",
            "method=dummy",
            "experiment=none",
            "tracking.experiment=dummy",
            f"paths.runs={runs}",
            f"hydra.searchpath=[file://{dummy_conf / 'conf'}]",
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "dummy s0: run" in done.stdout and "rmse" in done.stdout and "0.5" in done.stdout
    client = MlflowClient(tracking_uri(runs))
    [run] = client.search_runs([client.get_experiment_by_name("dummy").experiment_id])
    assert run.data.metrics["rmse"] == 0.5  # the description, led by the result:
    assert run.data.tags[NOTE_TAG] == "**Result:** `rmse` 0.5\n\n**A dummy method**"
    assert run.info.run_name == "dummy s0"

    sys.path.insert(0, str(dummy_conf / "code"))
    try:
        methods = registered([CONF_DIR, dummy_conf / "conf"])
        assert [m.name for m in methods][-1] == "dummy"  # paper "Z" sorts last
        found = reports(methods)
        assert found[-1].__name__ == "dummy_method"
        assert len(found) == len({r.__name__ for r in found})  # A's shared reports once
    finally:
        sys.path.remove(str(dummy_conf / "code"))


def test_the_job_and_tables_name_no_method():
    for path in ("pipeline/app.py", "pipeline/tables.py"):
        text = (ROOT / path).read_text()
        for name in ("neural_btf", "clustered", "pca", "brdf_map", "fourier"):
            assert name not in text, (path, name)


def test_every_method_config_names_its_method():
    from helpers import compose_config

    for path in sorted((CONF_DIR / "method").glob("*.yaml")):
        method = method_of(compose_config(f"method={path.stem}", "experiment=none"))
        assert isinstance(method, Method) and method.name == path.stem
        assert method.description and method.headline and method.reports


def test_a_spec_of_another_method_or_missing_is_refused():
    from helpers import compose_config

    cfg = compose_config("model=pca")
    cfg.method.spec = "pipeline.brdf_map.methods:BRDF_MAP"
    with pytest.raises(ConfigError, match="is method 'brdf_map'"):
        method_of(cfg)
    cfg.method.spec = "pipeline.btf.methods:NOPE"
    with pytest.raises(ConfigError, match="cannot import"):
        method_of(cfg)


@pytest.mark.parametrize(
    "override, hint",
    [
        # +btf.crop.szie: tests/test_refusals.py's BEFORE_ANY_JOB
        ("++btf.crop.szie=32", "did you mean btf.crop.size"),
        ("+method.prior_strenght=0.1", "did you mean method.prior_strength"),
    ],
)
def test_an_added_unknown_setting_is_refused_naming_the_closest(override, hint, tmp_path):
    experiment = "brdf_smoke" if "prior" in override else "smoke"
    done = pipeline_command(f"experiment={experiment}", f"paths.runs={tmp_path}", override)
    assert done.returncode != 0 and hint in done.stderr, done.stderr[-2000:]
    assert not (tmp_path / "mlflow.db").exists()  # refused before anything ran


def test_open_maps_groups_and_real_settings_may_be_added():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pipeline.core.settings import check_added_keys

    overrides = ["+tracking.tags.note=x", "++btf.crop.size=12", "experiment=smoke"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides)
        check_added_keys(cfg, overrides, CONF_DIR, compose=lambda o: compose("config", o))
        check_added_keys(
            cfg, ["+experiment_model=smoke_clustered", "+hydra/launcher=local"], CONF_DIR
        )  # groups
    assert not GlobalHydra.instance().is_initialized()
