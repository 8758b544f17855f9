"""``key=value`` command lines (pipeline/core/cli.py) and the developer commands that read
theirs with it: a bad argument is refused naming it (and the closest real key), before
torch loads."""

from dataclasses import dataclass

import pytest
from helpers import exits_before_torch

from benchmarks import profile_step, ubo2014_load
from benchmarks import render as render_bench
from pipeline.core import cli
from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, ListOf, OneOf
from pipeline.data import ubo2014_info


@dataclass(frozen=True)
class Toy:
    steps: int = 30
    threads: int | None = None
    mode: str = "fast"
    crop: tuple = (0, 0, 4, 4)
    runs: str = "runs"


KEYS = {
    "steps": ("steps", Integer(1), "training steps"),
    "threads": ("threads", Integer(1, optional=True), "threads (null: all)"),
    "mode": ("mode", OneOf("fast", "slow", True), "how"),
    "crop": ("crop", ListOf(Integer(0), 4), "[row, col, height, width]"),
    "paths.runs": ("runs", cli.Text(), "the runs folder"),
}


def test_values_are_read_as_yaml():
    assert cli.parse([], KEYS, Toy) == Toy()
    assert cli.parse(
        ["steps=5", "threads=null", "mode=true", "crop=[1, 2,3,4]", "paths.runs=/tmp/r"], KEYS, Toy
    ) == Toy(5, None, True, [1, 2, 3, 4], "/tmp/r")
    assert cli.read(["threads=2"], KEYS) == {"threads": 2}


@pytest.mark.parametrize(
    "argument, said",
    [
        ("step=5", "'step=5' is not a setting (did you mean steps?)"),
        ("--steps", "'--steps' is not a setting (did you mean steps?)"),
        ("runs=x", "'runs=x' is not a setting (did you mean paths.runs?)"),
        ("colour=red", "'colour=red' is not a setting: give key=value with a key among steps, "),
        ("steps=abc", "steps='abc' must be an integer >= 1"),
        ("steps=0", "steps=0 must be an integer >= 1"),
        ("threads=true", "threads=True must be an integer >= 1 or null"),
        ("mode=medium", "mode='medium' must be one of fast, slow, True"),
        ("crop=[0,0,4]", "crop=[0, 0, 4] must be a list of 4 items"),
        ("paths.runs=", "paths.runs=None must be a non-empty string"),
        ("crop=[0,0", "crop='[0,0' is not a value (YAML)"),
        ("steps", "steps needs a value: give steps=VALUE"),
        ("steps=1:30", "steps='1:30' must be an integer >= 1"),  # YAML 1.1 would say 90
        ("mode=on", "mode='on' must be one of fast, slow, True"),  # YAML 1.1 would say True
    ],
)
def test_a_bad_argument_is_refused_naming_it(argument, said):
    with pytest.raises(ConfigError) as raised:
        cli.read([argument], KEYS)
    assert str(raised.value).startswith(said)


def test_a_key_given_twice_is_refused():
    with pytest.raises(ConfigError, match="steps is given twice"):
        cli.read(["steps=1", "steps=2"], KEYS)


def test_help_lists_each_key_with_its_default(capsys):
    text = cli.usage("prog", KEYS, Toy(), "Summary:", notes="A note.")
    with pytest.raises(SystemExit) as done:
        cli.parse_args("prog", lambda argv: cli.parse(argv, KEYS, Toy), text, ["bad", "-h"])
    assert done.value.code == 0
    assert capsys.readouterr().out == text + "\n"
    assert text.startswith("usage: prog [key=value ...]\n\nSummary:\n  steps=30\n")
    for line in (
        "  threads=null",
        "  mode=fast",
        "  crop=[0,0,4,4]",
        "  paths.runs=runs",
        "      the runs folder",
        "\nA note.",
    ):
        assert line in text, line


def test_a_bad_command_line_exits_2_with_one_line_on_stderr(capsys):
    with pytest.raises(SystemExit) as done:
        cli.parse_args("prog", lambda argv: cli.parse(argv, KEYS, Toy), "usage", ["stps=1"])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("prog: error: 'stps=1' is not a setting (did you mean steps?)")
    assert err.count("\n") == 1


def test_the_command_is_the_first_word():
    assert cli.command_of(["info", "file=x"], ["info", "bench"]) == ("info", ["file=x"])
    with pytest.raises(ConfigError, match=r"unknown command 'inf' \(did you mean info\?\)"):
        cli.command_of(["inf"], ["info", "bench"])
    with pytest.raises(ConfigError, match="no command: give one of info, bench"):
        cli.command_of(["file=x"], ["info", "bench"])


# --- the commands -----------------------------------------------------------------------------


def test_the_render_benchmark_takes_key_value_settings():
    assert render_bench.parse(
        ["size=16", "spp=1", "crop=4", "threads=2"]
    ) == render_bench.RenderBenchSettings(size=16, spp=1, crop=4, threads=2)
    with pytest.raises(ConfigError, match=r"'sze=16' is not a setting .*\(did you mean size\?\)"):
        render_bench.parse(["sze=16"])


def test_the_ubo2014_commands_take_key_value_settings():
    settings = ubo2014_load.parse(
        ["crop=[0,0,10,10]", "components=4", "dtype=float32", "workdir=/tmp"]
    )
    assert settings == ubo2014_load.UBO2014LoadSettings(None, (0, 0, 10, 10), 4, "float32", "/tmp")
    assert ubo2014_info.parse(["file=a.btf"]).file == "a.btf"
    with pytest.raises(ConfigError, match=r"\(did you mean components\?\)"):
        ubo2014_load.parse(["component=4"])
    with pytest.raises(ConfigError, match="info needs file=PATH"):
        ubo2014_info.parse([])
    with pytest.raises(
        ConfigError, match=r"'crop=\[0,0,1,1\]' is not a setting of the info command"
    ):
        ubo2014_info.parse(["file=a.btf", "crop=[0,0,1,1]"])
    # components and dtype describe the file the benchmark writes: with file= they are ignored
    with pytest.raises(ConfigError, match="components, dtype: settings of the file the benchmark"):
        ubo2014_load.parse(["file=a.btf", "dtype=float32", "components=4"])
    assert ubo2014_load.parse(["file=a.btf", "crop=[0,0,1,1]"]).file == "a.btf"


def test_the_ubo2014_info_command_describes_a_file(tmp_path, capsys):
    path = ubo2014_load.write_paper_shaped(
        tmp_path / "small.btf", components=2, n_views=2, n_lights=3, size=4
    )
    ubo2014_info.main([f"file={path}"])
    assert "lights of view 0" in capsys.readouterr().out


def test_the_step_profiler_takes_key_value_settings():
    assert profile_step.parse([]) == profile_step.ProfileSettings(
        threads=(1, 2), steps=30, rounds=3, setups=("before", "encoder", "after")
    )
    assert profile_step.parse(
        ["threads=1", "steps=2", "rounds=1", "setups=after,before"]
    ) == profile_step.ProfileSettings(threads=(1,), steps=2, rounds=1, setups=("after", "before"))
    assert profile_step.parse(["threads=[1,4]", "setups=[after]"]).threads == (1, 4)
    with pytest.raises(ConfigError, match=r"\(did you mean rounds\?\)"):
        profile_step.parse(["round=2"])
    with pytest.raises(ConfigError, match="setups='aftr' must be one of before, encoder, after"):
        profile_step.parse(["setups=aftr"])


def test_each_command_refuses_a_bad_key_before_torch_loads():
    """Each command's main: exit 2 on a misspelt key, with the closest key named, and
    torch not imported."""
    codes, torch_loaded, stderr = exits_before_torch(
        [
            ("benchmarks.profile_step", ["step=1"]),
            ("benchmarks.render", ["sze=1"]),
            ("benchmarks.ubo2014_load", ["dtype=float64"]),
        ]
    )
    assert codes == [2, 2, 2] and not torch_loaded
    assert "(did you mean steps?)" in stderr and "(did you mean size?)" in stderr
    assert "dtype='float64' must be one of float16, float32" in stderr


@pytest.mark.parametrize(
    "text, value",
    [
        ("30", 30),
        ("-3", -3),
        ("1.5", 1.5),
        ("1e-3", 0.001),
        (".inf", float("inf")),
        ("true", True),
        ("False", False),
        ("null", None),
        ("[1,2]", [1, 2]),
        ("1:30", "1:30"),
        ("on", "on"),
        ("yes", "yes"),
        ("0x10", "0x10"),
        ("1_000", "1_000"),
    ],
)
def test_values_are_read_as_yaml_1_2_reads_them(text, value):
    """As Hydra's overrides: YAML 1.2's plain scalars, not PyYAML's 1.1 sexagesimal
    integers, yes/on booleans, hexadecimal or underscored numbers."""
    assert cli.read_value(text) == value
