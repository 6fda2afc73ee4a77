"""Lone changes in latent frames: a pixel whose log intensity moved since the latent image started while fewer than
`need` of its 8 neighbours moved the same way is shown at its start.

Why: between APS frames each pixel moves by its own events only, so one pixel's extra or missing event (threshold
mismatch, a noise event, one lost to the refractory period, where its log intensity sat in its dead band) shows as
a dot, a whole step of c (x1.55 at c = 0.44), and a region the events cross and leave is left speckled where ON and
OFF events did not cancel. Neighbouring pixels see the same motion: a moving edge changes neighbours together and
is shown as it is, and so is a line one pixel wide except its ends. The deblurred frame's own guard against one
pixel's errors is edi.smoothing; this one serves the frames after it (the node's `--latent-denoise`).

`lone_changes_u8` is the test over a whole frame (compiled, and its numpy reference); `LoneChanges` holds where each
pixel of a latent image started and redoes the test, frame by frame, only in the 8x8 tiles near the events applied
since the previous frame. Kept up to date event by event instead (each event's pixel and, when the sign of its
change flips, its neighbours' counts and shown values), the test cost more, not less: on a busy scene pixels flip
back and forth around their start on most events (95 against 11 ns an event for the propagation alone, on the 6 s
240x180 demo).
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
                    need: int = LONE_NEED, eps: float = LONE_EPS) -> np.ndarray:
    """`display` as a new (H, W) uint8 array, except at pixels whose log intensity moved by more than `eps` since
    `log_start` while fewer than `need` of their 8 neighbours on the sensor moved the same way: those show
    `start_display`. The change is log_lat - log_start in float32. log images (H, W) float32, displays (H, W)
    uint8. (LoneChanges keeps the result between frames and redoes it only where events fell.)"""
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
    tw, th = _tiles_across(width), _tiles_across(height)
    out = np.empty((height, width), np.uint8)
    _kernels_lone.update_tiles(*(np.ascontiguousarray(a).reshape(-1) for a in arrays), width, height, int(need),
                               float(eps), np.zeros((height + 2) * (width + 2), np.int8), np.ones(tw * th, np.uint8),
                               tw, out.reshape(-1))
    return out


def _tiles_across(n: int) -> int:
    return (n + (1 << _kernels_lone.TILE_SHIFT) - 1) >> _kernels_lone.TILE_SHIFT


class LoneChanges:
    """Where each pixel of a latent image started (its log value, and as it was shown then), and the latent frame as
    lone_changes_u8 shows it, kept up to date where the image changed: `restart` at a reference, `restart_at`
    where pixels start again (a flicker flag, the fall-back to the APS), `touched` for the events applied to the
    image, `changed_everywhere` when the whole display was rewritten, `image` for a frame.

    Between two frames only the pixels near the events applied can change verdict, so `image` redoes the test in the
    8x8 tiles those events marked (each event marks the tiles of its 3x3 neighbourhood) and copies the rest from the
    previous frame: the same frame as the whole-frame test, bit for bit, for a cost that follows where the events
    fell (a frame of 1000 events marks 3-56 % of the tiles on the recordings at hand) rather than the sensor size."""

    def __init__(self, width: int, height: int, *, need: int = LONE_NEED, eps: float = LONE_EPS) -> None:
        self.width, self.height, self.need, self.eps = width, height, int(need), float(eps)
        self.start = np.zeros((height, width), np.float32)
        self.start_display = np.zeros((height, width), np.uint8)
        self._tw = _tiles_across(width)
        self._tiles = np.ones(self._tw * _tiles_across(height), np.uint8)  # marked: all, until the first image()
        self._signs = np.zeros((height + 2) * (width + 2), np.int8)  # each pixel's sign of change; border 0
        self._shown = np.zeros(width * height, np.uint8)
        self.tiles_updated = 0  # tiles whose test was redone, over all image() calls (for the cost figures)

    def copy(self) -> "LoneChanges":
        twin = LoneChanges(self.width, self.height, need=self.need, eps=self.eps)
        np.copyto(twin.start, self.start)
        np.copyto(twin.start_display, self.start_display)
        return twin  # its tiles are all marked: its first image() does the whole test

    def restart(self, log_lat: np.ndarray, display: np.ndarray) -> None:
        """Every pixel starts here."""
        np.copyto(self.start, log_lat)
        np.copyto(self.start_display, display)
        self._tiles.fill(1)

    def restart_at(self, pixels: np.ndarray, log_lat: np.ndarray, display: np.ndarray) -> None:
        """`pixels` (flat indices) start again at their value now."""
        flat = np.asarray(pixels, np.int64).reshape(-1)
        self.start.reshape(-1)[flat] = log_lat.reshape(-1)[flat]
        self.start_display.reshape(-1)[flat] = display.reshape(-1)[flat]
        if flat.size:
            _kernels_lone.mark_pixel_tiles(flat, self.width, self.height, self._tw, self._tiles)

    def touched(self, x: np.ndarray, y: np.ndarray) -> None:
        """Events at (x, y) were applied to the latent image (its log values and display)."""
        if x.size:
            _kernels_lone.mark_tiles(x, y, self.width, self.height, self._tw, self._tiles)

    def changed_everywhere(self) -> None:
        """The display or the log image was rewritten as a whole."""
        self._tiles.fill(1)

    def image(self, log_lat: np.ndarray, display: np.ndarray) -> np.ndarray:
        """`display` without its lone changes since the start, as a new array."""
        if not _backend.have_numba():  # the numpy reference, whole frame; the next compiled call redoes every tile
            self._tiles.fill(1)
            return lone_changes_u8(log_lat, self.start, display, self.start_display, need=self.need, eps=self.eps)
        self.tiles_updated += _kernels_lone.update_tiles(
            log_lat.reshape(-1), self.start.reshape(-1), display.reshape(-1), self.start_display.reshape(-1),
            self.width, self.height, self.need, self.eps, self._signs, self._tiles, self._tw, self._shown)
        return self._shown.reshape(self.height, self.width).copy()
