"""Lone changes in latent frames: a pixel whose log intensity moved since the latent image started while fewer than
`need` of its 8 neighbours moved the same way is shown at its start.

Why: between APS frames each pixel moves by its own events only, so one pixel's extra or missing event (threshold
mismatch, a noise event, one lost to the refractory period, where its log intensity sat in its dead band) shows as
a dot, a whole step of c (x1.55 at c = 0.44), and a region the events cross and leave is left speckled where ON and
OFF events did not cancel. Neighbouring pixels see the same motion: a moving edge changes neighbours together and
is shown as it is, and so is a line one pixel wide except its ends. The deblurred frame's own guard against one
pixel's errors is edi.smoothing; this one serves the frames after it (the node's `--latent-denoise`).

`lone_changes_u8` is the test over a whole frame (compiled, and its numpy reference); `LoneChanges` holds where each
pixel of a latent image started. Kept up to date event by event instead (each event's pixel and, when the sign of
its change flips, its neighbours' counts and shown values), the test cost more, not less: on a busy scene pixels
flip back and forth around their start on most events (95 against 11 ns an event for the propagation alone, on
the 6 s 240x180 demo, against ~0.1 ms a frame for the pass over the frame).
"""

from __future__ import annotations

import numpy as np

from edi_live.edi import _backend, _kernels_lone

LONE_NEED = 2
"""Neighbours that must have changed the same way for a pixel's change to be shown: 1 kept pairs of dots, 3 started
to eat thin moving detail (docs/accuracy.md, "Lone changes in latent frames")."""
LONE_EPS = 1e-4
"""A log change at most this large is no change: float32 sums of steps that cancel leave ~1e-7 (a step is >= 0.01)."""


def lone_changes_u8(log_lat: np.ndarray, log_start: np.ndarray, display: np.ndarray, start_display: np.ndarray, *,
                    need: int = LONE_NEED, eps: float = LONE_EPS, scratch: np.ndarray | None = None) -> np.ndarray:
    """`display` as a new (H, W) uint8 array, except at pixels whose log intensity moved by more than `eps` since
    `log_start` while fewer than `need` of their 8 neighbours on the sensor moved the same way: those show
    `start_display`. The change is log_lat - log_start in float32. log images (H, W) float32, displays (H, W) uint8;
    `scratch`: new_lone_scratch(W, H), kept between calls."""
    arrays = [np.asarray(a) for a in (log_lat, log_start, display, start_display)]
    if (any(a.shape != arrays[0].shape for a in arrays) or arrays[0].ndim != 2
            or [a.dtype for a in arrays] != [np.float32, np.float32, np.uint8, np.uint8]):
        raise ValueError(f"lone_changes_u8 needs two (H, W) float32 log images and two uint8 displays of one shape "
                         f"(got {[f'{a.shape} {a.dtype}' for a in arrays]})")
    log_lat, log_start, display, start_display = arrays
    height, width = log_lat.shape
    if not _backend.have_numba():
        d = log_lat - log_start
        sign = (d > eps).astype(np.int8) - (d < -eps).astype(np.int8)
        pad = np.pad(sign, 1)  # off the sensor: no change, which never matches a changed pixel
        same = sum((pad[dy:dy + height, dx:dx + width] == sign).astype(np.int8)
                   for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1))
        return np.where((sign != 0) & (same < need), start_display, display)
    if scratch is None or scratch.dtype != np.int8 or scratch.shape != (_scratch_size(width, height),):
        scratch = new_lone_scratch(width, height)
    out = np.empty((height, width), np.uint8)
    grid = _words((height + 2) * (width + 2))
    _kernels_lone.lone_changes_u8(*(np.ascontiguousarray(a).reshape(-1) for a in arrays), width, height, int(need),
                                  float(eps), scratch[:(height + 2) * (width + 2)], scratch[grid:], out.reshape(-1))
    return out


def new_lone_scratch(width: int, height: int) -> np.ndarray:
    """Work space for lone_changes_u8, kept between frames: a sign grid with a border and the per-pixel verdicts, each
    on 8-byte boundaries (the verdicts are read 8 at a time); any int8 array of its length will do: lone_changes_u8
    sets what it reads."""
    return np.zeros(_scratch_size(width, height), np.int8)


def _words(n: int) -> int:
    return -(-n // 8) * 8


def _scratch_size(width: int, height: int) -> int:
    return _words((height + 2) * (width + 2)) + _words(width * height)


class LoneChanges:
    """Where each pixel of a latent image started (its log value, and as it was shown then), for lone_changes_u8:
    `restart` at a reference, `restart_at` where pixels start again (a flicker flag, the fall-back to the APS)."""

    def __init__(self, width: int, height: int, *, need: int = LONE_NEED, eps: float = LONE_EPS) -> None:
        self.width, self.height, self.need, self.eps = width, height, int(need), float(eps)
        self.start = np.zeros((height, width), np.float32)
        self.start_display = np.zeros((height, width), np.uint8)
        self._scratch = new_lone_scratch(width, height) if _backend.have_numba() else None

    def copy(self) -> "LoneChanges":
        twin = LoneChanges.__new__(LoneChanges)
        twin.width, twin.height, twin.need, twin.eps = self.width, self.height, self.need, self.eps
        twin.start, twin.start_display = self.start.copy(), self.start_display.copy()
        twin._scratch = None if self._scratch is None else new_lone_scratch(self.width, self.height)
        return twin

    def restart(self, log_lat: np.ndarray, display: np.ndarray) -> None:
        """Every pixel starts here."""
        np.copyto(self.start, log_lat)
        np.copyto(self.start_display, display)

    def restart_at(self, pixels: np.ndarray, log_lat: np.ndarray, display: np.ndarray) -> None:
        """`pixels` (flat indices) start again at their value now."""
        self.start.reshape(-1)[pixels] = log_lat.reshape(-1)[pixels]
        self.start_display.reshape(-1)[pixels] = display.reshape(-1)[pixels]

    def image(self, log_lat: np.ndarray, display: np.ndarray) -> np.ndarray:
        """`display` without its lone changes since the start, as a new array."""
        return lone_changes_u8(log_lat, self.start, display, self.start_display, need=self.need, eps=self.eps,
                               scratch=self._scratch)
