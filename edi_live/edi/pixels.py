"""Per-pixel bookkeeping around the EDI: hot-pixel statistics, background-activity (noise) and flicker filters, the
unreliable-pixel score and its dilation, and marking the pixels that had events.

All inputs are time-ordered events of EVENT_DTYPE; masks are (H, W) bool or flat bool of H*W.
"""

from __future__ import annotations

import numpy as np

from edi_live.edi import _backend, _kernels_pixels
from edi_live.edi.selection import select

_NO_WORDS = np.zeros(0, np.uint64)  # dilate: a mask that cannot be read a word at a time


def hot_pixel_mask(counts: np.ndarray, duration_us: float, *, min_rate_hz: float = 300.0,
                   rel_factor: float = 10.0) -> np.ndarray:
    """Hot pixels from per-pixel event counts over `duration_us`: a pixel is hot when its rate exceeds
    `min_rate_hz` AND its count exceeds `rel_factor` times the mean count over active pixels.

    Moving edges spread their events over many pixels, so they raise the mean; a stuck pixel fires alone.
    Accumulate `counts` over several frames so edges average out.
    """
    counts = np.asarray(counts)
    active = counts > 0
    if not active.any() or duration_us <= 0:
        return np.zeros(counts.shape, dtype=bool)
    mean_active = float(counts[active].mean())
    rate_hz = counts * (1e6 / float(duration_us))
    return (rate_hz > min_rate_hz) & (counts > rel_factor * mean_active)


def new_activity_map(width: int, height: int) -> np.ndarray:
    """State for background_activity_keep: latest event time per pixel, padded by one pixel, 'long ago'."""
    return np.full((height + 2, width + 2), -(2**62), dtype=np.int64)


def background_activity_keep(events: np.ndarray, width: int, height: int, last_t: np.ndarray,
                             dt_us: int) -> np.ndarray:
    """Per event: True when one of its 8 neighbours fired within dt_us before it (time-ordered input).
    `last_t` (from new_activity_map) is updated in place, so successive batches form one stream."""
    keep = np.empty(len(events), dtype=bool)
    if _backend.have_numba():
        _kernels_pixels.background_activity(events["t"], events["x"], events["y"], width, height, last_t, int(dt_us), keep)
        return keep
    for i, (t, x, y) in enumerate(zip(events["t"].tolist(), events["x"].tolist(), events["y"].tolist())):
        if x >= width or y >= height:
            keep[i] = False
            continue
        block = last_t[y:y + 3, x:x + 3]
        keep[i] = bool(((t - block) <= dt_us).sum() - ((t - block[1, 1]) <= dt_us) > 0)
        last_t[y + 1, x + 1] = t
    return keep


def new_activity_state() -> np.ndarray:
    """State for activity_verdicts (see there)."""
    return np.zeros(7, np.int64)


def activity_verdicts(events: np.ndarray, width: int, height: int, last_t: np.ndarray, state: np.ndarray, *,
                      check_us: int, window_us: int, max_noise_hz: float, sigmas: float, margin: int,
                      support_us: int, scratch: list | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene-activity test (edi_live.activity) over time-ordered events, carried across calls in `last_t`
    (new_activity_map: background_activity_keep's state) and `state` (new_activity_state). A window of
    check_us spans (multiples of check_us) is judged at the end of each span that held events, at its first event
    after it: active when its n events exceed what max_noise_hz per pixel gives, or its s supported ones what
    noise at its own rate gives (p = 1 - exp(-8 r support_us), + sigmas binomial deviations + margin). It
    restarts after an active verdict or once it covers window_us. Returns (index of that event, active, span end)
    per verdict: views into `scratch` (a list the caller keeps between calls, for the buffers) if given."""
    n = len(events)
    if scratch is None or not scratch or len(scratch[0]) < n:
        bufs = [np.empty(max(n, 1024), dt) for dt in (np.int64, np.bool_, np.int64)]
        if scratch is None:
            scratch = bufs
        else:
            scratch[:] = bufs
    at, active, end = scratch
    params = np.array([check_us, window_us, max_noise_hz, sigmas, margin, support_us], np.float64)
    kernel = _kernels_pixels.activity_verdicts if _backend.have_numba() else \
        _kernels_pixels.activity_verdicts.py_func
    k = kernel(events["t"], events["x"], events["y"], int(width), int(height), last_t, state, params, at, active,
               end)
    return at[:k], active[:k], end[:k]


def supported_events_keep(events: np.ndarray, width: int, height: int, dt_us: int) -> np.ndarray:
    """Per event of one batch: True when one of its 8 neighbours fired within dt_us before OR after it.
    The two-sided, stateless form of the background-activity filter, for a whole exposure at once."""
    fwd = background_activity_keep(events, width, height, new_activity_map(width, height), dt_us)
    rev = events[::-1].copy()
    rev["t"] = -rev["t"]
    bwd = background_activity_keep(rev, width, height, new_activity_map(width, height), dt_us)[::-1]
    return fwd | bwd


def isolated_event_mask(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels with exactly one event in `events` and no event in their 8 neighbours.

    A background-activity filter at window granularity: such lone events are most likely noise.
    """
    import cv2  # local: only this optional filter needs it, and importing cv2 costs ~25 ms

    idx, _, _ = select(events, width, height, None, None, None)
    counts = np.bincount(idx, minlength=width * height).reshape(height, width).astype(np.float32)
    neigh = cv2.boxFilter(counts, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) - counts
    return (counts == 1) & (neigh == 0)


def decay_hot_counts(hot_counts: np.ndarray, frame_counts: np.ndarray, decay: float, duration_us: float, *,
                     min_rate_hz: float, rel_factor: float) -> np.ndarray:
    """In place: hot_counts = decay * hot_counts + frame_counts, and frame_counts is reset to 0 (flat arrays).
    Returns the flat bool hot-pixel mask of hot_pixel_mask() on the decayed counts over `duration_us`."""
    if _backend.have_numba():
        hot = np.empty(hot_counts.size, bool)
        _kernels_pixels.update_hot(hot_counts, frame_counts, float(decay), float(duration_us), float(min_rate_hz),
                                   float(rel_factor), hot)
        return hot
    hot_counts *= decay
    hot_counts += frame_counts
    frame_counts.fill(0)
    return hot_pixel_mask(hot_counts, duration_us, min_rate_hz=min_rate_hz, rel_factor=rel_factor)


class FlickerState:
    """Per-pixel state of `flicker_cycles` (flat over width * height pixels)."""

    def __init__(self, width: int, height: int) -> None:
        npix = width * height
        self.width, self.height = width, height
        self.bits = np.zeros(npix, np.uint8)  # 1: last event ON, 2: an event was seen, 4: flagged, >> 3: run
        self.times = np.full((npix, 2), -(2**62), np.int64)  # latest OFF -> ON switch, latest regular one
        self.changes = np.zeros(1, np.int64)  # flag changes so far
        self.read = np.zeros(1, np.int64)  # events the latest flicker_cycles call read (all, unless span_us)
        self.flagged_now = np.empty(npix, np.int64)  # scratch: a pixel is flagged at most once per call

    @property
    def flagged(self) -> np.ndarray:
        """Flat bool: the flagged pixels (a new array)."""
        return (self.bits & 4) != 0

    @property
    def run(self) -> np.ndarray:
        """Flat: each pixel's consecutive regular cycles (up to 31)."""
        return self.bits >> 3


def flicker_cycles(events: np.ndarray, state: FlickerState, *, min_period_us: int, max_period_us: int, cycles: int,
                   hold_us: int, span_us: int = 0) -> np.ndarray:
    """Feed time-ordered events to the flicker state. A pixel is flagged once `cycles` consecutive cycles (one
    OFF -> ON switch to the next) lasted min..max_period_us, or twice that (a switch the pixel missed, or a lamp
    flickering at the mains frequency itself), and stays flagged while such cycles come within hold_us
    (state.flagged; state.changes counts flag changes). Returns the flat pixels these events flagged. With
    `span_us`, it stops at the first event past the span (t // span_us) in which a flag changed: state.read[0]
    says how many events it read."""
    s = state
    if _backend.have_numba():
        n = _kernels_pixels.flicker_cycles(events["t"], events["x"], events["y"], events["p"], s.width, s.height,
                                           s.bits, s.times, int(min_period_us), int(max_period_us), int(cycles),
                                           int(hold_us), int(span_us), s.flagged_now, s.changes, s.read)
        return s.flagged_now[:n].copy()
    n, stop_span = 0, None
    s.read[0] = len(events)
    for i, (t, x, y, on) in enumerate(zip(events["t"].tolist(), events["x"].tolist(), events["y"].tolist(),
                                          events["p"].tolist())):
        if stop_span is not None and t // span_us != stop_span:
            s.read[0] = i
            break
        changes = int(s.changes[0])
        if x >= s.width or y >= s.height:
            continue
        q = y * s.width + x
        b = int(s.bits[q])
        if on:
            if b & 3 == 2:
                d = t - s.times[q, 0]
                s.times[q, 0] = t
                if min_period_us <= d <= max_period_us or 2 * min_period_us <= d <= 2 * max_period_us:
                    b = b + 8 if b < 248 else b
                    s.times[q, 1] = t
                else:
                    b &= 7
                if not b & 4 and b >> 3 >= cycles:
                    b |= 4
                    s.changes[0] += 1
                    if n < s.flagged_now.size:
                        s.flagged_now[n] = q
                        n += 1
            b |= 3
        else:
            b = (b & ~1) | 2
        if b & 4 and t - s.times[q, 1] > hold_us:
            b &= 3
            s.changes[0] += 1
        s.bits[q] = b
        if span_us > 0 and stop_span is None and int(s.changes[0]) != changes:
            stop_span = t // span_us
    return s.flagged_now[:n].copy()


def dilate(mask: np.ndarray, offsets: list[tuple[int, int]]) -> np.ndarray:
    """(H, W) bool: `mask` OR-ed with itself shifted by every (dy, dx) offset, without wrap-around at the borders
    (a new array; `mask` is not changed)."""
    if _backend.have_numba():
        out = np.array(mask, dtype=bool, order="C")  # the mask itself is in the result, whatever the offsets
        off = np.asarray(offsets, np.int64).reshape(-1, 2)
        m = np.ascontiguousarray(mask, bool)
        flat = m.reshape(-1)
        # 8 pixels a word (a pass of ~3 µs at 240x180, not ~15), if the mask's memory allows a uint64 view
        words = flat[:flat.size // 8 * 8].view(np.uint64) if flat.ctypes.data % 8 == 0 else _NO_WORDS
        _kernels_pixels.dilate(m, words, off[:, 0].copy(), off[:, 1].copy(), out)
        return out
    out = mask.copy()
    h, w = mask.shape
    for dy, dx in offsets:
        out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
            mask[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


def update_contradictions(score: np.ndarray, own: np.ndarray, n_on: np.ndarray, n_off: np.ndarray,
                          log_prev: np.ndarray, log_cur: np.ndarray, informative_prev: np.ndarray,
                          informative_cur: np.ndarray, c: tuple[float, float], busy: np.ndarray | None, *,
                          min_events: int, min_change: float, relative: float, saturated_limit: float, decay: float,
                          release: float) -> np.ndarray:
    """One frame pair of the unreliable-pixel score (pixel_masks.UnreliablePixels): flat float32 `score` decays
    (except at `own` pixels still `busy`) and gains 1 where the pair's events contradict the frames. Returns the
    new flat bool `own`: score >= release where it was own, >= 1 elsewhere."""
    n_on, n_off = n_on.reshape(-1), n_off.reshape(-1)
    own = own.reshape(-1)
    if _backend.have_numba():
        out = np.empty(score.size, bool)
        use_busy = busy is not None
        _kernels_pixels.contradictions(score, own, n_on, n_off, log_prev.reshape(-1), log_cur.reshape(-1),
                                       informative_prev.reshape(-1), informative_cur.reshape(-1), float(c[0]),
                                       float(c[1]), busy.reshape(-1) if use_busy else n_on, use_busy,
                                       int(min_events), float(min_change), float(relative),
                                       float(saturated_limit), float(decay), float(release), out)
        return out
    active = np.flatnonzero((n_on + n_off) >= min_events)
    if busy is None:
        score *= decay
    else:
        held = own & (busy.reshape(-1) >= min_events)
        score *= np.where(held, np.float32(1.0), np.float32(decay))
    if active.size:
        pred = c[0] * n_on[active] - c[1] * n_off[active]
        both = informative_prev.reshape(-1)[active] & informative_cur.reshape(-1)[active]
        obs = log_cur.reshape(-1)[active] - log_prev.reshape(-1)[active]
        size = np.abs(pred)
        bad = np.where(both, (size >= min_change) & (np.abs(pred - obs) > relative * size), size > saturated_limit)
        score[active[bad]] += 1.0
    return np.where(own, score >= release, score >= 1.0)


def mark_event_pixels(events: np.ndarray, width: int, height: int, out: np.ndarray) -> None:
    """Set flat bool `out` True at the pixels of `events`; events off the (width, height) sensor are ignored."""
    x, y = events["x"], events["y"]
    if _backend.have_numba():
        _kernels_pixels.mark_pixels(x, y, width, height, out)
        return
    keep = (x < width) & (y < height)
    out[y[keep].astype(np.intp) * width + x[keep]] = True

