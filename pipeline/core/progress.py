"""Progress of a long loop: a tqdm bar on the terminal, and a line in the job's log every
:data:`LOG_EVERY_S` seconds (how far, the rate and the time left), which keeps no bar.

>>> total = 0
>>> for chunk in progress(range(3), "evaluate", unit="chunk"):
...     total += chunk
>>> total
3

``with progress(None, "decode", total=n) as bar: bar.update(k)`` counts by hand.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator

from tqdm.auto import tqdm

log = logging.getLogger("pipeline.progress")

# Seconds between two log lines of one loop (the first after as long).
LOG_EVERY_S = 30.0


def _clock(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"


class progress:
    """Iterate ``iterable`` (or count to ``total`` with :meth:`update`) showing progress.

    Parameters
    ----------
    iterable : iterable or None
    what : str
        What the loop does, as the bar and the log lines name it.
    total : int, optional
        Units in all; ``len(iterable)`` when it has one.
    unit : str
        What one unit is ("texel", "chunk", "direction").
    scale : int
        Units that one item of ``iterable`` counts for (a chunk of 64 texels: 64).
    """

    def __init__(
        self,
        iterable: Iterable | None,
        what: str,
        *,
        total: int | None = None,
        unit: str = "it",
        scale: int = 1,
    ):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable) * scale
        self.iterable, self.what, self.unit, self.scale = iterable, what, unit, scale
        self.total = total
        self.done = 0
        self.postfix = ""
        self.start = self.last_log = time.monotonic()
        self.bar = tqdm(
            total=total,
            desc=what,
            unit=unit,
            leave=False,
            mininterval=1.0,
            disable=not sys.stderr.isatty(),
        )

    def update(self, count: int = 1) -> None:
        """``count`` more units done (never past ``total``: a last, shorter chunk)."""
        if self.total is not None:
            count = min(count, self.total - self.done)
        self.done += count
        self.bar.update(count)
        now = time.monotonic()
        if now - self.last_log >= LOG_EVERY_S:
            self.last_log = now
            log.info("%s", self.line(now))

    def set_postfix(self, **values) -> None:
        """Values shown after the count (``epoch=3, loss="0.002"``), as tqdm's."""
        self.bar.set_postfix(**values)
        self.postfix = ", ".join(f"{key}={value}" for key, value in values.items())

    def line(self, now: float | None = None) -> str:
        """``what: done/total unit (x %), rate, elapsed, left``."""
        elapsed = max((now or time.monotonic()) - self.start, 1e-9)
        rate = self.done / elapsed
        text = f"{self.what}: {self.done:,}"
        if self.total:
            text += f"/{self.total:,} {self.unit} ({100 * self.done / self.total:.0f} %)"
        else:
            text += f" {self.unit}"
        text += f", {rate:,.1f} {self.unit}/s, {_clock(elapsed)} elapsed"
        if self.total and self.done:
            text += f", ~{_clock((self.total - self.done) / rate)} left"
        return f"{text}, {self.postfix}" if self.postfix else text

    def close(self) -> None:
        self.bar.close()

    def __iter__(self) -> Iterator:
        try:
            for item in self.iterable:
                yield item
                self.update(self.scale)
        finally:
            self.close()

    def __enter__(self) -> progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
