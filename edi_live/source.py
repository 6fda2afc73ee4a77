"""The `Source` protocol that every driver implements (live USB, emulated USB, AEDAT4 replay).

The node cannot tell sources apart: it enters the context, iterates, and calls `stop()` from another thread
to end the iteration early.
"""

from __future__ import annotations

import threading
from typing import Callable, Iterator, Protocol, runtime_checkable

from edi_live.datatypes import Packet, SourceInfo, SourceStatus


@runtime_checkable
class Source(Protocol):
    info: SourceInfo

    def __enter__(self) -> "Source":
        """Open and start the device or file. Raises SourceError subclasses with a one-line message."""
        ...

    def __exit__(self, *exc: object) -> None:
        """Stop the device (or close the file) and release everything. Safe to call after a failure."""
        ...

    def __iter__(self) -> Iterator[Packet | None]:
        """Yield time-ordered packets; None when nothing arrived within ~0.1 s (so the caller can check
        for stop). Ends at the end of a recording or after stop(). A fault raises SourceError after every
        packet received before the fault has been yielded."""
        ...

    def stop(self) -> None:
        """Ask the iteration to end soon. Thread-safe, idempotent."""
        ...

    def status(self) -> SourceStatus:
        """Counters (packets, events, drops, backlog) so far."""
        ...


def stop_from_another_thread(stop: Callable[[], None]) -> None:
    """Call a source's stop() on a short-lived thread of its own. For a signal handler: it runs on the thread that
    may be inside the source (opening it, waiting for a camera), holding a lock that stop() takes."""
    threading.Thread(target=stop, name="source-stop", daemon=True).start()
