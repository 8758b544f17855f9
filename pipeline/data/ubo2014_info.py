"""``python -m pipeline.data.ubo2014_info file=PATH``: a DFMF file's header facts and its view
and light directions with the indices ``dataset.views`` / ``dataset.lights`` accept.

``--help`` lists the settings (:data:`KEYS`). The peak memory of loading a crop is a
developer benchmark beside the package: ``python -m benchmarks.ubo2014_load``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import cli
from pipeline.core.errors import ConfigError
from pipeline.data.ubo2014_header import describe, read_dfmf

PROG = "python -m pipeline.data.ubo2014_info"


@dataclass(frozen=True)
class UBO2014InfoSettings:
    """The file to describe; :data:`KEYS` describes the key."""

    file: str | None = None


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {"file": ("file", cli.Text(optional=True), "a .btf (DFMF) file")}


COMMAND = cli.Command(
    PROG,
    KEYS,
    UBO2014InfoSettings,
    "Header facts, views and lights of the .btf file (file= required). "
    "Settings and their defaults:",
    what="the info command",
)


def parse(argv: list[str]) -> UBO2014InfoSettings:
    """:class:`UBO2014InfoSettings` from ``key=value`` arguments; raises
    :class:`ConfigError` naming a bad one, or when ``file`` is missing."""
    settings = COMMAND.parse(argv)
    if settings.file is None:
        raise ConfigError("info needs file=PATH, the .btf file to describe")
    return settings


def main(argv: list[str] | None = None) -> None:
    """Print the header facts, the views and view 0's lights of ``file`` (degrees)."""
    dfmf = read_dfmf(Path(COMMAND.parse_args(argv, parse).file))
    for key, value in describe(dfmf).items():
        print(f"{key:>18}: {value}")
    print("views (index: theta, phi in degrees):")
    for index, (theta, phi) in enumerate(np.degrees(dfmf.view_angles)):
        print(f"  {index:4d}: {theta:7.2f} {phi:7.2f}")
    print("lights of view 0 (index: theta, phi in degrees):")
    for index, (theta, phi) in enumerate(np.degrees(dfmf.light_angles[0])):
        print(f"  {index:4d}: {theta:7.2f} {phi:7.2f}")


if __name__ == "__main__":
    main()
