"""The stage context every method's runners share: the config, the cache, and what ran.
A runner calls :meth:`Context.run` with its stage's name and code version (bump it when a
code change alters the output); the cache decides whether anything needs computing."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import Container, DictConfig, OmegaConf

from pipeline.core.cache import Entry, StageCache
from pipeline.core.memory import stage_peak
from pipeline.core.run_log import NO_RUN, RunLog


@dataclass
class Context:
    """What every runner needs: the config, the cache, the job's run to log to, and the
    keys used so far."""

    cfg: DictConfig
    cache: StageCache
    log: RunLog = NO_RUN
    keys: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    peak_rss_mb: dict[str, float] = field(default_factory=dict)

    @classmethod
    def from_config(cls, cfg: DictConfig, log: RunLog = NO_RUN) -> Context:
        """The context of a job; opening its cache removes what killed jobs left there."""
        cache = StageCache(cfg.paths.cache)
        cache.remove_stale_temporaries()
        return cls(cfg, cache, log)

    def run(
        self, stage: str, settings, inputs: dict[str, Entry], compute, *, version: str
    ) -> Entry:
        """Run (or fetch) ``stage`` at code ``version`` with its own ``settings``."""
        if not isinstance(version, str) or not version:
            raise TypeError(f"stage {stage!r} needs a version string, got {version!r}")
        input_keys = {name: e.key for name, e in inputs.items()}
        with stage_peak() as peak:
            entry = self.cache.run(stage, version, settings, input_keys, compute)
        self.keys[stage] = entry.key
        self.seconds[stage] = entry.seconds
        self.peak_rss_mb[stage] = peak["mb"]
        return entry


def plain_settings(node):
    """A plain dict/list copy of a config node (resolved); other values pass through."""
    if isinstance(node, Container):
        return OmegaConf.to_container(node, resolve=True)
    return node


def folder_fingerprint(root: Path) -> dict:
    """Count, total size, newest mtime and a hash of the names of the files under ``root``:
    one stat per file, in the load key, so that a dataset edited in place (renamed files
    included: angles are read from the names) is decoded again."""
    count, size, newest, names = 0, 0, 0, []
    for folder, _dirs, files in os.walk(root):
        relative = os.path.relpath(folder, root)
        for name in files:
            st = os.stat(os.path.join(folder, name))
            count, size, newest = count + 1, size + st.st_size, max(newest, st.st_mtime_ns)
            names.append(name if relative == "." else f"{relative}/{name}")
    listing = "\n".join(sorted(names)).encode()
    return {
        "files": count,
        "bytes": size,
        "mtime_ns": newest,
        "names": hashlib.sha256(listing).hexdigest()[:16],
    }
