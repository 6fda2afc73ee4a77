"""Deblurring an APS frame off the worker thread: while the original reconstructor computes the new reference on
the "edi-deblur" helper thread, the worker streams latent frames from a streaming copy that still holds the
previous reference. The events the copy applies meanwhile are kept (`catchup`) and replayed into the original
when the worker adopts it again.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

import numpy as np

from edi_live.datatypes import Reconstruction
from edi_live.reconstruction import Reconstructor
from edi_live.ring import FrameEntry


class PendingDeblur:
    """One APS frame being deblurred on the "edi-deblur" helper thread by the master reconstructor, while the
    worker streams latent frames from a copy that still holds the previous reference. The events the copy
    applies meanwhile are kept (`catchup`) and replayed into the master when it is adopted."""

    def __init__(self, master: Reconstructor, entry: FrameEntry, events: np.ndarray, arrival_ns: int, send: bool,
                 wake: Callable[[], None]) -> None:
        self.master, self.entry, self.send = master, entry, send
        self.catchup: list[np.ndarray] = []
        self.gap = False
        self.result: Reconstruction | None = None
        self.error: BaseException | None = None
        self.deblur_ms = 0.0
        self.done = threading.Event()
        self._wake = wake
        self._thread = threading.Thread(target=self._run, args=(events, arrival_ns), name="edi-deblur",
                                        daemon=True)
        self._thread.start()

    def _run(self, events: np.ndarray, arrival_ns: int) -> None:
        t0 = time.perf_counter()
        try:
            self.result = self.master.on_frame(self.entry.frame, events, arrival_ns)
        except BaseException as exc:  # re-raised on the worker thread when adopted
            self.error = exc
        finally:
            self.deblur_ms = (time.perf_counter() - t0) * 1e3
            self.done.set()
            self._wake()
