"""Waiting in tests for a state another thread or process reaches: poll a predicate until it holds, with a
deadline (a failed assertion when it passes), for states that no event or queue announces (a socket's
server-side count, a thread's flag)."""

from __future__ import annotations

import threading
import time
from typing import Callable


def wait_until(predicate: Callable[[], object], timeout_s: float = 10.0, poll_s: float = 0.005) -> None:
    """Return once predicate() is true; fail the test if it is not within timeout_s."""
    pause = threading.Event()  # never set: a wait that a clock patched by the test cannot shorten
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached within the timeout"
        pause.wait(poll_s)
