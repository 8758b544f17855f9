"""Errors the pipeline raises for bad input: each names the file or the value at fault."""

import signal


class PipelineError(Exception):
    """Base class: a problem with the user's input or configuration, not a bug."""


class DataError(PipelineError, ValueError):
    """A dataset file or folder is missing, malformed or holds invalid values."""


class ConfigError(PipelineError, ValueError):
    """A setting is out of range or inconsistent with the data."""


class StoreError(PipelineError, RuntimeError):
    """The MLflow store cannot be opened or written (a damaged database, say)."""


class Stopped(SystemExit):
    """The job was stopped by a signal (SIGTERM, SIGINT, SIGHUP): not an error of the
    job. Its exit status is 128 + the signal's number, as a shell reports a killed job."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum

    def __str__(self) -> str:
        return f"stopped by signal {self.signum} ({signal.Signals(self.signum).name})"
