"""Errors the pipeline raises for bad input: each names the file or the value at fault."""


class PipelineError(Exception):
    """Base class: a problem with the user's input or configuration, not a bug."""


class DataError(PipelineError, ValueError):
    """A dataset file or folder is missing, malformed or holds invalid values."""


class ConfigError(PipelineError, ValueError):
    """A setting is out of range or inconsistent with the data."""


class StoreError(PipelineError, RuntimeError):
    """The MLflow store cannot be opened or written (a damaged database, say)."""
