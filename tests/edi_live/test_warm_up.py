"""What the person at the terminal sees while the kernels compile (edi_live.warm_up): a first run after installing
compiles for 15-30 s before the input opens, and printed nothing in that time. The compile is stood in for by a
reconstructor factory that waits; nothing here depends on how long anything takes."""

from __future__ import annotations

import logging
import threading

from edi_live.config import EdiConfig
from edi_live.warm_up import SLOW_NOTICE, warm_up


class _Seen(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []
        self.notice = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
        if record.getMessage() == SLOW_NOTICE:
            self.notice.set()


def _watching() -> tuple[_Seen, logging.Logger]:
    seen, logger = _Seen(), logging.getLogger("edi_live.node")
    logger.addHandler(seen)
    return seen, logger


def test_a_slow_warm_up_says_once_why_the_start_waits_and_at_info_level():
    seen, logger = _watching()
    level = logger.level
    logger.setLevel(logging.INFO)
    waited = []

    def compiling(*args):  # returns only once the notice is out (or gives up), as a cold compile would
        waited.append(seen.notice.wait(timeout=60))
        raise RuntimeError("stand-in for the compile")  # ends the warm-up: its failures are not fatal

    try:
        warm_up(compiling, EdiConfig(), slow_after_s=0.0)
    finally:
        logger.removeHandler(seen)
        logger.setLevel(level)
    assert waited == [True]
    notices = [r for r in seen.records if r.getMessage() == SLOW_NOTICE]
    assert len(notices) == 1 and notices[0].levelno == logging.INFO
    assert "first run" in SLOW_NOTICE and "15-30 s" in SLOW_NOTICE


def test_a_warm_up_that_ends_before_the_threshold_says_nothing_then_or_later(monkeypatch):
    seen, logger = _watching()
    level = logger.level
    logger.setLevel(logging.INFO)
    timers = []

    class Recorded(threading.Timer):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            timers.append(self)

    monkeypatch.setattr(threading, "Timer", Recorded)

    def cached(*args):
        raise RuntimeError("stand-in for kernels loaded from the cache")

    try:
        warm_up(cached, EdiConfig(), slow_after_s=3600.0)
        # "later": the timer is cancelled by the time warm_up returns (a pending one would speak an hour later)
        assert timers and all(timer.finished.is_set() for timer in timers)
        for timer in timers:
            timer.join(timeout=60)  # a cancelled timer ends at once without calling
    finally:
        logger.removeHandler(seen)
        logger.setLevel(level)
    assert not [r for r in seen.records if r.getMessage() == SLOW_NOTICE]
