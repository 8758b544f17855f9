"""``python -m benchmarks.train key=value ...``: its settings, read and refused without torch."""

import doctest
import re
from dataclasses import fields

import pytest
from helpers import exits_before_torch

from benchmarks import train_settings
from benchmarks.train_settings import KEYS, BenchSettings, parse, parse_args, usage
from pipeline.core.errors import ConfigError


def test_key_value_arguments_set_the_bench():
    settings = parse(
        [
            "steps=2",
            "threads=1",
            "device=cuda",
            "paths.runs=/tmp/r",
            "mlflow=false",
            "paper_run=200",
            "load_size=256",
        ]
    )
    assert settings == BenchSettings(
        steps=2, threads=1, device="cuda", runs="/tmp/r", mlflow=False, paper_run=200, load_size=256
    )
    assert parse([]) == BenchSettings()
    assert parse(["threads=null"]).threads is None


@pytest.mark.parametrize(
    "argument, named",
    [
        ("--steps", "'--steps' is not a setting of the bench"),
        ("steps", "steps needs a value: give steps=VALUE"),
        # the key is paths.runs, as elsewhere
        ("runs=x", "'runs=x' is not a setting of the bench (did you mean paths.runs?)"),
        ("step=3", "'step=3' is not a setting of the bench (did you mean steps?)"),
        ("steps=abc", "steps='abc' must be an integer >= 1"),
        ("steps=0", "steps=0 must be an integer >= 1"),
        ("steps=1.5", "steps=1.5 must be an integer"),
        ("threads=0", "threads=0 must be an integer >= 1 or null"),
        ("device=gpu", "device='gpu' must be one of cpu, cuda"),
        ("mlflow=maybe", "mlflow='maybe' must be one of True, False"),
        ("paper_run=-1", "paper_run=-1 must be an integer >= 0"),
        ("paths.runs=", "paths.runs=None must be a non-empty string"),
    ],
)
def test_a_bad_argument_is_refused_naming_it(argument, named):
    with pytest.raises(ConfigError, match=re.escape(named)):
        parse([argument])


def test_help_lists_every_setting_with_its_default(capsys):
    with pytest.raises(SystemExit) as done:
        parse_args(["steps=3", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert text == usage() + "\n"
    for key in KEYS:
        assert f"  {key}=" in text, key
    assert "  steps=30\n" in text and "  threads=null\n" in text and "  mlflow=true\n" in text
    assert sorted(field for field, _, _ in KEYS.values()) == sorted(
        f.name for f in fields(BenchSettings)
    )


def test_a_bad_argument_is_answered_before_torch_loads():
    """The command's error (exit 2, as argparse's) and its --help come before the seconds
    torch takes to import."""
    codes, torch_loaded, stderr = exits_before_torch(
        [("benchmarks.train", ["steps=abc"]), ("benchmarks.train", ["--help"])]
    )
    assert codes == [2, 0] and not torch_loaded
    assert "python -m benchmarks.train: error: steps='abc' must be" in stderr


def test_the_docstring_examples_run():
    """The module's ``>>>`` examples (tests/test_layout.py runs the package's, not these)."""
    results = doctest.testmod(train_settings, optionflags=doctest.ELLIPSIS)
    assert results.attempted > 0 and results.failed == 0
