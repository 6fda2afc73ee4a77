"""A pipe whose writer is done, as bash's <(...) hands one over, for the readers of files given on the command line."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


@contextlib.contextmanager
def written_pipe(data: bytes) -> Iterator[str]:
    """The path (/proc/self/fd/N) of a pipe holding `data` whose write end is closed; closed again afterwards."""
    read_end, write_end = os.pipe()
    try:
        os.write(write_end, data)
        os.close(write_end)
        yield f"/proc/self/fd/{read_end}"
    finally:
        os.close(read_end)
