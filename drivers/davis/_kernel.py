"""The hot loop of the word decoder: timestamps (wrap multiplier, reset), DVS polarity events, and the
positions/times of every other word for the slower APS/IMU/special state machine.

`scan` runs the numba-compiled loop (numba is a hard dependency). `scan_numpy` is a vectorised reference with
identical results, kept only for the tests that check the kernel against it (and for the benchmark's
comparison, `python -m tools.bench_usb_decode`). Events are written straight into the 16-byte EVENT_DTYPE layout
viewed as int64 pairs: [t, x | y << 16 | p << 32].

State vector (int64[8]): wrap_add, current (device µs), last_y (-1 = unknown), offset (added to device time),
started (a timestamp or wrap word was seen), bad (words dropped as out of range), last_out (last event time
emitted), backwards (events whose time went backwards, e.g. after garbage words; clamped so output stays sorted).
"""

from __future__ import annotations

import numba
import numpy as np

# (importing edi_live settles numba's cache folder, edi_live.kernel_cache, before the kernel below is defined)
from edi_live import kernel_cache  # noqa: F401

WRAP_STEP = 0x8000
S_WRAP, S_CURRENT, S_LAST_Y, S_OFFSET, S_STARTED, S_BAD, S_LAST_OUT, S_BACKWARDS = range(8)


def new_state(offset_us: int = 0) -> np.ndarray:
    return np.array([0, 0, -1, offset_us, 0, 0, -(2**62), 0], dtype=np.int64)


def _scan_py(words, state, cols, rows, swap, ev, ctrl_idx, ctrl_t):
    """The loop `scan` runs compiled by numba (plain Python here). Returns (n_events, n_ctrl)."""
    wrap_add = state[0]
    current = state[1]
    last_y = state[2]
    offset = state[3]
    started = state[4]
    bad = state[5]
    last_out = state[6]
    backwards = state[7]
    n_ev = 0
    n_ctrl = 0
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        if w & 0x8000:
            current = wrap_add + (w & 0x7FFF)
            started = 1
            continue
        code = w >> 12
        data = w & 0xFFF
        if code == 2 or code == 3:
            if data < cols and last_y >= 0:
                t = current + offset
                if t < last_out:
                    backwards += 1
                    t = last_out
                last_out = t
                ev[n_ev, 0] = t
                if swap:
                    ev[n_ev, 1] = last_y | (data << 16) | ((code & 1) << 32)
                else:
                    ev[n_ev, 1] = data | (last_y << 16) | ((code & 1) << 32)
                n_ev += 1
            else:
                bad += 1
        elif code == 1:
            if data < rows:
                last_y = data
            else:
                bad += 1
        elif code == 7:
            wrap_add += WRAP_STEP * data
            current = wrap_add
            started = 1
        else:
            if code == 0 and data == 1:  # timestamp reset: device time restarts at 0, output time continues
                if started:
                    offset += current
                wrap_add = 0
                current = 0
            ctrl_idx[n_ctrl] = i
            ctrl_t[n_ctrl] = current + offset
            n_ctrl += 1
    state[0] = wrap_add
    state[1] = current
    state[2] = last_y
    state[3] = offset
    state[4] = started
    state[5] = bad
    state[6] = last_out
    state[7] = backwards
    return n_ev, n_ctrl


def _segment_np(w, state, cols, rows, swap):
    """Vectorised scan of a reset-free segment; updates state, returns (ev int64[n,2], ctrl_idx, ctrl_t)."""
    n = w.shape[0]
    hi = (w >> 12).astype(np.int64)
    data = (w & 0xFFF).astype(np.int64)
    is_ts = hi >= 8
    is_wrap = hi == 7
    wrap_cum = state[S_WRAP] + np.cumsum(np.where(is_wrap, data * WRAP_STEP, 0))
    setter = is_ts | is_wrap
    val = wrap_cum + np.where(is_ts, w.astype(np.int64) & 0x7FFF, 0)
    pos = np.arange(n)
    idx = np.maximum.accumulate(np.where(setter, pos, -1))
    cur = np.where(idx >= 0, val[np.maximum(idx, 0)], state[S_CURRENT])
    set_y = (hi == 1) & (data < rows)
    idy = np.maximum.accumulate(np.where(set_y, pos, -1))
    ly = np.where(idy >= 0, data[np.maximum(idy, 0)], state[S_LAST_Y])
    is_x = (hi == 2) | (hi == 3)
    good = is_x & (data < cols) & (ly >= 0)
    t = cur[good] + state[S_OFFSET]
    if t.size:
        mono = np.maximum.accumulate(np.concatenate([[state[S_LAST_OUT]], t]))[1:]
        state[S_BACKWARDS] += int(np.count_nonzero(mono != t))
        t = mono
        state[S_LAST_OUT] = t[-1]
    x, y, p = data[good], ly[good], hi[good] & 1
    if swap:
        x, y = y, x
    ev = np.empty((t.shape[0], 2), dtype=np.int64)
    ev[:, 0] = t
    ev[:, 1] = x | (y << 16) | (p << 32)
    is_ctrl = (hi == 0) | (hi == 4) | (hi == 5) | (hi == 6)
    ctrl_idx = np.flatnonzero(is_ctrl)
    ctrl_t = cur[ctrl_idx] + state[S_OFFSET]
    state[S_BAD] += int(np.count_nonzero(is_x & ~good)) + int(np.count_nonzero((hi == 1) & (data >= rows)))
    if n:
        state[S_WRAP] = wrap_cum[-1]
        state[S_CURRENT] = cur[-1]
        state[S_LAST_Y] = ly[-1]
        if setter.any():
            state[S_STARTED] = 1
    return ev, ctrl_idx, ctrl_t


def scan_numpy(words: np.ndarray, state: np.ndarray, cols: int, rows: int, swap: bool):
    """Reference for tests: split at timestamp-reset words (rare) and scan each segment vectorised."""
    resets = np.flatnonzero(words == 1)
    evs, cidx, cts = [], [], []
    start = 0
    for r in [*resets.tolist(), words.shape[0]]:
        ev, ci, ct = _segment_np(words[start:r], state, cols, rows, swap)
        evs.append(ev)
        cidx.append(ci + start)
        cts.append(ct)
        if r < words.shape[0]:
            if state[S_STARTED]:
                state[S_OFFSET] += state[S_CURRENT]
            state[S_WRAP] = 0
            state[S_CURRENT] = 0
            cidx.append(np.array([r], dtype=np.int64))
            cts.append(np.array([state[S_OFFSET]], dtype=np.int64))
        start = r + 1
    return np.concatenate(evs), np.concatenate(cidx), np.concatenate(cts)


_scan_nb = numba.njit(cache=True, nogil=True)(_scan_py)


def scan(words: np.ndarray, state: np.ndarray, cols: int, rows: int, swap: bool):
    """Scan `words`, updating `state`: (events as int64[n, 2], indices of control words, their times)."""
    n = words.shape[0]
    ev = np.empty((n, 2), dtype=np.int64)
    ctrl_idx = np.empty(n, dtype=np.int64)
    ctrl_t = np.empty(n, dtype=np.int64)
    n_ev, n_ctrl = _scan_nb(words, state, cols, rows, swap, ev, ctrl_idx, ctrl_t)
    return ev[:n_ev], ctrl_idx[:n_ctrl], ctrl_t[:n_ctrl]
