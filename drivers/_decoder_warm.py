"""Imported only by the decoding children's forkserver (drivers.prefetch preloads it): decodes a tiny recording
once, so the numba kernels of the AEDAT4 reader are loaded in the server and every child forked from it starts
with them ready (a child that loads them itself needs ~0.4 s for its first packet).

A failure here is harmless: the child then loads the kernels on first use, as it would without this module.
"""

from __future__ import annotations

import os
import tempfile


def _warm() -> None:
    import numpy as np

    from drivers.replay import merged_packets
    from edi_live.aedat4 import Aedat4Writer
    from edi_live.datatypes import EVENT_DTYPE

    events = np.zeros(8, EVENT_DTYPE)
    events["t"] = np.arange(8)
    fd, path = tempfile.mkstemp(suffix=".aedat4")
    os.close(fd)
    try:
        with Aedat4Writer(path, 4, 4) as writer:
            writer.write_events(events)
        for _ in merged_packets(path):
            pass
    finally:
        os.unlink(path)


try:
    _warm()
except Exception:  # noqa: BLE001 - see the module docstring
    pass
