"""Progress reaches the job's log, not only a terminal's bar."""

import logging

from pipeline.core import progress as progress_module
from pipeline.core.progress import progress


def test_a_long_loop_logs_how_far_it_is_with_its_postfix(monkeypatch, caplog):
    monkeypatch.setattr(progress_module, "LOG_EVERY_S", 0.0)
    caplog.set_level(logging.INFO, logger="pipeline.progress")
    bar = progress(range(0, 10, 4), "evaluate", total=10, unit="texel", scale=4)
    items = list(bar)
    assert items == [0, 4, 8] and bar.done == 10  # the last, shorter chunk is not overcounted
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0].startswith("evaluate: 4/10 texel (40 %)") and "left" in lines[0]
    assert lines[-1].startswith("evaluate: 10/10 texel (100 %)")
    with progress(None, "train", total=3, unit="step") as counted:
        counted.set_postfix(epoch=1, loss="0.5")
        counted.update()
    assert caplog.records[-1].getMessage().endswith("epoch=1, loss=0.5")
