"""SIGINT/SIGTERM/SIGHUP for the command line: the first one stops the node cleanly, at any moment from the first
line of `cli.main()` (a signal during start-up stops the node as soon as it exists, before it opens anything); any
later one is ignored with one log line while the bounded stop finishes. SIGHUP (the terminal or ssh session went
away) stops like SIGTERM, unless it was already ignored when we started (`nohup edi-live ...`).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from typing import Any, Iterator

log = logging.getLogger("edi_live")
# SIGHUP's default action kills the process on the spot: --out left without its table, queued frames lost
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class StopRequested(BaseException):
    """A stop signal came while edi-live was still reading its options or compiling its kernels
    (StopSignals.raising): nothing has been opened, so the program simply ends, as cleanly as a stopped node does.
    A BaseException, like KeyboardInterrupt: the warm-up's "any failure here is not fatal" must not swallow it."""


class StopSignals:
    """SIGINT/SIGTERM/SIGHUP, handled from the first line of main(): the first one stops the node cleanly (a signal that
    arrives while edi-live starts up stops the node as soon as it exists, before any data flows); any later one
    is ignored with one line. The stop itself is bounded (every join has a timeout), and a second Ctrl-C that
    interrupted it would cut the file finalisation short, so the summary would no longer match --out."""

    def __init__(self) -> None:
        self.received: str | None = None
        self._node: Any = None
        self._repeated = False
        self._previous: dict[int, Any] = {}
        self._raise = False

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # (an in-process call from a thread: Python allows handlers on the main thread only)
        for sig in STOP_SIGNALS:
            if sig == getattr(signal, "SIGHUP", None) and signal.getsignal(sig) == signal.SIG_IGN:
                continue  # nohup: the user asked to outlive the terminal
            self._previous[sig] = signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, old in self._previous.items():
            signal.signal(sig, old)
        self._previous.clear()

    def ignore_from_now_on(self) -> None:
        if self._previous:
            for sig in self._previous:
                signal.signal(sig, signal.SIG_IGN)

    def attach(self, node: Any) -> None:
        self._node = node
        if self.received is not None:
            node.stop()

    def _handle(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.received is not None:
            if not self._repeated:
                self._repeated = True
                log.warning("%s: already stopping; the received data and files are being finalised", name)
            return
        self.received = name
        log.info("%s: stopping", name)
        if self._node is not None:
            self._node.stop()
        if self._raise:
            self._raise = False
            raise StopRequested(name)

    @contextlib.contextmanager
    def raising(self) -> Iterator[None]:
        """Within: a stop signal (or one received before) raises StopRequested at once, for the start-up steps
        that may wait with nothing yet to stop cleanly: a --config FIFO that nothing writes kept Ctrl-C waiting
        for its 5 s and then ended as a usage error; a cold kernel compile kept SIGTERM waiting 14 s (15-30 s
        and more on a small computer, past a service manager's stop timeout)."""
        if self.received is not None:
            raise StopRequested(self.received)
        self._raise = True
        try:
            yield
        finally:
            self._raise = False
