"""Saying in one line that the process ran out of memory, and which limit it met; and warning at start about an
open-files limit too small for the subscribers.

Under a memory limit (`ulimit -v`, a service's MemoryMax= is enforced differently: by the kernel's OOM killer)
running out surfaces as whatever failed first: numpy's MemoryError while the ring is allocated, an ImportError
"failed to map segment from shared object" as cv2 or numba's LLVM library loads, or llvmlite's "Could not
find/load shared object file" raised while handling that. The CLI turns each into a ResourceError that names
the limit, instead of an internal error or "the main thread failed: ImportError: ...".
"""

from __future__ import annotations

import errno
import logging
import resource

from edi_live.errors import ResourceError

log = logging.getLogger("edi_live")

_SIGNS = ("failed to map segment", "cannot allocate memory")
FEW_OPEN_FILES = 256  # the node itself holds ~16; each subscriber or DV client takes one more


def check_open_files() -> None:
    """Warn when the open-files limit is low: libzmq refuses a subscriber it has no file descriptor for without a
    word (under `ulimit -n 64`, 48 of 100 subscribers were served and the node said nothing)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < FEW_OPEN_FILES:
        log.warning("only %d open files are allowed (ulimit -n): subscribers beyond what fits are refused without "
                    "a word; raise the limit (ulimit -n 1024, or LimitNOFILE= in a systemd unit)", soft)


def out_of_memory(exc: BaseException) -> ResourceError | None:
    """A ResourceError if `exc`, or an exception that caused it, is the process running out of memory."""
    cause = _memory_cause(exc)
    if cause is None:
        return None
    first = (str(cause).strip().splitlines() or [""])[0]
    detail = f"{type(cause).__name__}: {first}" if first else type(cause).__name__
    return ResourceError(f"out of memory ({detail}): {_limit_advice()}")


def _memory_cause(exc: BaseException) -> BaseException | None:
    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
    while todo:
        e = todo.pop(0)
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, MemoryError):
            return e
        if isinstance(e, OSError) and e.errno == errno.ENOMEM:
            return e
        if isinstance(e, (OSError, ImportError)) and any(sign in str(e).lower() for sign in _SIGNS):
            return e
        todo += [e.__cause__, e.__context__]
    return None


def _limit_advice() -> str:
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    raise_it = "raise the limit, or give a smaller --ring-events (the default ring alone takes 64 MiB)"
    if soft == resource.RLIM_INFINITY:
        return "the machine has no free memory left; close other programs, or give a smaller --ring-events"
    return (f"this process may use at most {soft / 2**20:.0f} MiB of address space (ulimit -v {soft // 1024}); "
            f"{raise_it}")
