"""numba kernels over pixels: the background-activity filter, the hot-pixel statistics, the flicker cycles, the
unreliable-pixel score and dilation, and the marking of pixels with events.

Private to edi_live.edi (see its public functions and their numpy references).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _first_at_or_after


@njit(cache=True, nogil=True, inline="always")
def _neighbour_fired(last_t, xi, yi, ti, dt_us):
    """Whether one of the 8 neighbours of pixel (xi, yi) fired within dt_us before ti (last_t: the padded map)."""
    for dy in range(3):
        for dx in range(3):
            if (dy != 1 or dx != 1) and ti - last_t[yi + dy, xi + dx] <= dt_us:
                return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _neighbours_fired(last_t, xi, yi, ti, dt_us):
    """_neighbour_fired as 0/1 without a branch per neighbour (which one fired first is unpredictable)."""
    a = last_t[yi]
    b = last_t[yi + 1]
    c = last_t[yi + 2]
    lim = ti - dt_us
    m = max(max(max(a[xi], a[xi + 1]), max(a[xi + 2], b[xi])), max(max(b[xi + 2], c[xi]), max(c[xi + 1], c[xi + 2])))
    return np.int64(m >= lim)


@njit(cache=True, nogil=True)
def background_activity(t, x, y, width, height, last_t, dt_us, keep):
    """Background-activity filter: keep[i] when one of the 8 neighbours fired within dt_us before event i.
    last_t is a (height + 2, width + 2) int64 map of each pixel's latest event time (border never written)."""
    for i in range(t.size):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi >= width or yi >= height:
            keep[i] = False
            continue
        keep[i] = _neighbour_fired(last_t, xi, yi, t[i], dt_us)
        last_t[yi + 1, xi + 1] = t[i]


@njit(cache=True, nogil=True)
def update_hot(hot_counts, frame_counts, decay, duration_us, min_rate_hz, rel_factor, hot):
    """hot_counts = decay * hot_counts + frame_counts (frame_counts is reset to 0), then the hot-pixel rule of
    edi.hot_pixel_mask on the result, written into `hot` (flat bool)."""
    total = 0.0
    n_active = 0
    for q in range(hot_counts.size):
        v = hot_counts[q] * decay + frame_counts[q]
        frame_counts[q] = 0
        hot_counts[q] = v
        if v > 0:
            total += v
            n_active += 1
    if n_active == 0 or duration_us <= 0:
        hot[:] = False
        return
    limit = rel_factor * (total / n_active)
    scale = 1e6 / duration_us
    for q in range(hot_counts.size):
        v = hot_counts[q]
        hot[q] = v * scale > min_rate_hz and v > limit


@njit(cache=True, nogil=True)
def select_pixels(x, y, width, height, keep):
    """Indices of the events whose pixel is in range and marked in `keep` (flat uint8), in input order."""
    out = np.empty(x.size, dtype=np.int64)
    m = 0
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        if keep[np.int64(y[i]) * width + x[i]]:
            out[m] = i
            m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def flicker_cycles(t, x, y, p, width, height, bits, times, lo_us, hi_us, cycles, hold_us, span_us, flagged_now, changes,
                   read):
    """Mains-flicker cycles per pixel. State, flat over pixels: `bits` (1 = last event ON, 2 = an event was seen,
    4 = flagged, bits 3-7 = run: consecutive regular cycles, up to 31) and `times` (n, 2): the latest OFF -> ON
    switch (onset) and the latest regular one. An onset ends a cycle and starts the next; a cycle lo_us..hi_us
    long, or twice that (a missed switch), is regular; `cycles` regular ones in a row flag the pixel, which stays
    flagged while regular cycles keep coming within hold_us. Writes the pixels flagged by these events into
    `flagged_now` and returns how many; changes[0] counts every flag change (on and off). Most events repeat
    their pixel's last polarity: they touch one byte (and one time when flagged). With span_us > 0 it stops at the
    first event past the span_us-long span of the event clock in which a flag changed; read[0] = events read."""
    n = 0
    stop_span = np.int64(-1)
    for i in range(t.size):
        if stop_span >= 0 and t[i] // span_us != stop_span:
            read[0] = i
            return n
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi >= width or yi >= height:
            continue
        q = yi * width + xi
        b = np.int64(bits[q])
        on = np.int64(p[i])
        # one test for "ON after OFF" (bits 0-1 == 2 and p == 1), no branch on the polarity itself: polarities
        # alternate unpredictably from event to event (a branch on them cost ~2 ns an event), switches are rarer
        if ((b & 3) | (on << 2)) == 6:  # a cycle ends
            ti = t[i]
            d = ti - times[q, 0]
            times[q, 0] = ti
            if lo_us <= d <= hi_us or 2 * lo_us <= d <= 2 * hi_us:
                if b < 248:
                    b += 8
                times[q, 1] = ti
            else:
                b &= 7
            if (b & 4) == 0 and (b >> 3) >= cycles:
                b |= 4
                changes[0] += 1
                if span_us > 0 and stop_span < 0:
                    stop_span = t[i] // span_us
                if n < flagged_now.size:  # full only if pixels were flagged again within the call
                    flagged_now[n] = q
                    n += 1
        b = (b & ~1) | 2 | on  # seen, and the polarity
        if (b & 4) != 0 and t[i] - times[q, 1] > hold_us:
            b &= 3
            changes[0] += 1
            if span_us > 0 and stop_span < 0:
                stop_span = t[i] // span_us
        bits[q] = b
    read[0] = t.size
    return n


@njit(cache=True, nogil=True)
def contradictions(score, own, n_on, n_off, log_prev, log_cur, inf_prev, inf_cur, c_on, c_off, busy, use_busy,
                   min_events, min_change, relative, saturated_limit, decay, release, out):
    """pixels.update_contradictions in one pass (float32 score and thresholds as numpy computes them)."""
    decay32 = np.float32(decay)
    release32 = np.float32(release)
    one = np.float32(1.0)
    for q in range(score.size):
        if not (use_busy and own[q] and busy[q] >= min_events):
            score[q] *= decay32
        if n_on[q] + n_off[q] >= min_events:
            pred = c_on * n_on[q] - c_off * n_off[q]
            size = abs(pred)
            if inf_prev[q] and inf_cur[q]:
                obs = log_cur[q] - log_prev[q]
                bad = size >= min_change and abs(pred - obs) > relative * size
            else:
                bad = size > saturated_limit
            if bad:
                score[q] += one
        out[q] = score[q] >= release32 if own[q] else score[q] >= one


@njit(cache=True, nogil=True)
def dilate(mask, words, dy, dx, out):
    """out (a copy of mask, (H, W)) |= mask shifted by every (dy[j], dx[j]), clipped at the borders: each marked
    pixel stamps the offsets around it (marked pixels are few; no pass per offset). `words`: the mask's first
    8 * words.size pixels as uint64 (may be empty), so that 8 unmarked pixels are skipped at once."""
    h, w = mask.shape
    flat = mask.reshape(-1)
    for k in range(words.size):
        if words[k] != 0:
            for q in range(8 * k, 8 * k + 8):
                if flat[q]:
                    _stamp(q // w, q % w, h, w, dy, dx, out)
    for q in range(8 * words.size, flat.size):
        if flat[q]:
            _stamp(q // w, q % w, h, w, dy, dx, out)


@njit(cache=True, nogil=True, inline="always")
def _stamp(y, x, h, w, dy, dx, out):
    for j in range(dy.size):
        yy = y + dy[j]
        xx = x + dx[j]
        if 0 <= yy < h and 0 <= xx < w:
            out[yy, xx] = True


@njit(cache=True, nogil=True)
def mark_pixels(x, y, width, height, out):
    """out[q] = True at every event's pixel on the sensor (flat bool)."""
    for i in range(x.size):
        if x[i] < width and y[i] < height:
            out[np.int64(y[i]) * width + x[i]] = True


@njit(cache=True, nogil=True, inline="always")
def _count_bound(max_noise_hz, npix, span_us, sigmas, margin):
    """The most events noise gives a window of span_us (µs), in the verdict's own order of operations: a bound
    rounded otherwise (max_noise_hz * npix * span_us first) can fall on the other side of a whole count."""
    most = max_noise_hz * (npix * span_us * 1e-6)
    return most + sigmas * np.sqrt(most) + margin


@njit(cache=True, nogil=True)
def _span_decided_by_count(t, i, span_end, room, tail_us):
    """Where the span that starts at event i ends (the index of the first event past it) when the span holds more
    than `room` events and the read goes on for `tail_us` past its end (a span nearer the read's end is never
    skipped: the next read's tests may read its times); -1 otherwise. Two probes rule most spans out before the
    bisection."""
    size = t.size
    need = np.int64(room) + 1  # the count that decides it
    if room < 0.0:
        need = 1
    if i + need >= size or t[i + need - 1] >= span_end or t[size - 1] < span_end + tail_us:
        return -1
    return _first_at_or_after(t, span_end, i + need, size)


@njit(cache=True, nogil=True)
def _tested_from(t, j, check_us, fewest):
    """From event j, which starts a span with a fresh window (the span before it was active by its count), the
    first event whose span is not known to be active by its count alone: its neighbour tests may count, and so
    may every store within support_us before it. Spans decided by the count follow one another in a busy scene."""
    size = t.size
    while True:
        end = (t[j] // check_us) * check_us + check_us
        k = _first_at_or_after(t, end, j, size)
        if k == size or k - j <= fewest:  # the span runs past this read, or its count does not decide it
            return j
        j = k


@njit(cache=True, nogil=True)
def activity_verdicts(t, x, y, width, height, last_t, state, params, out_at, out_active, out_end):
    """The activity test of edi.activity_verdicts over time-ordered events: the background-activity filter
    (background_activity's rule and `last_t` map) and the windows, in one pass. state (int64): window start, end of
    the latest span with events, events and supported events in the window, windows and active windows closed, 1
    once an event was seen. params: check_us, window_us, max_noise_hz, sigmas, margin, support_us. Writes one
    verdict per span judged (the index of the first event after it, active, the span's end); returns how many.

    Only the verdicts are the contract: neighbour tests and times no verdict can depend on are skipped. Once a
    window holds more events than noise could give in it, its verdict is active whatever the supported count: the
    neighbour test is skipped for its remaining events. And a span that starts in this read, ends in it and holds
    more events than that (two probes of the time-ordered events, then a bisection) is skipped whole when no test
    can read its times: when it ends more than support_us before the first event whose span its count alone does
    not decide (in this read, after the run of such spans, or the read's last event). A busy scene's long reads
    then cost a few probes per span (the 6 s demo recording in 22k-event reads, alone: 2.0 against 3.8 ns an
    event); short ones (a paced stream's 1 ms packets) go event by event, as before.
    """
    check_us, window_us, support_us = np.int64(params[0]), np.int64(params[1]), np.int64(params[5])
    max_noise_hz, sigmas, margin = params[2], params[3], params[4]
    npix = width * height
    fewest = _count_bound(max_noise_hz, npix, check_us, sigmas, margin)  # a one-span window's bound
    # the state in locals for the loop (kept in memory, each event paid a load and a store of the counts: the
    # compiler cannot tell `state` from the time map it writes)
    begin_w, span_end, n, s = state[0], state[1], state[2], state[3]
    windows, active_windows, started = state[4], state[5], state[6]
    sure = np.inf  # events in the window above which its verdict is active by the count alone
    if started != 0:
        sure = _count_bound(max_noise_hz, npix, span_end - begin_w, sigmas, margin)
    size = t.size
    chain_end = -1  # _tested_from's answer holds for spans that start before it
    nv = 0
    skip_to = 0  # events before it belong to a span its count decided: done
    for i in range(size):
        if i < skip_to:
            continue
        ti = t[i]
        # events are time-ordered and a span ends at a multiple of check_us, so only an event at or past the
        # span's end starts another: the division (the loop's costliest step) is done there only
        if started == 0 or ti >= span_end:
            begin = (ti // check_us) * check_us
            if started == 0:
                begin_w = begin
                started = 1
            else:
                pixel_s = npix * (span_end - begin_w) * 1e-6
                active = False
                if s > margin or n > fewest:
                    p = 1.0 - np.exp(-8.0 * (n / pixel_s) * support_us * 1e-6)
                    mean = n * p
                    active = (n > sure
                              or s > mean + sigmas * np.sqrt(mean * (1.0 - p)) + margin)
                out_at[nv] = i
                out_active[nv] = active
                out_end[nv] = span_end
                nv += 1
                if active or span_end - begin_w >= window_us:
                    windows += 1
                    active_windows += 1 if active else 0
                    begin_w = begin
                    n = 0
                    s = 0
            span_end = begin + check_us
            sure = _count_bound(max_noise_hz, npix, span_end - begin_w, sigmas, margin)
            j = _span_decided_by_count(t, i, span_end, sure - n, support_us)
            if j >= 0:  # the span ends in this read, active by its count
                if j >= chain_end:
                    chain_end = _tested_from(t, j, check_us, fewest)
                if t[j - 1] < t[chain_end] - support_us:  # no later test reads its times: nothing to do
                    n += j - i
                    skip_to = j
                    continue
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < width and yi < height:
            if n <= sure:
                s += _neighbours_fired(last_t, xi, yi, ti, support_us)
            last_t[yi + 1, xi + 1] = ti
        n += 1
    state[0], state[1], state[2], state[3] = begin_w, span_end, n, s
    state[4], state[5], state[6] = windows, active_windows, started
    return nv


@njit(cache=True, nogil=True)
def remask_divisor(old, use_old, new, use_new, seen, on, off, two, counting, back):
    """RunningDivisor.remask's pass over the pixels (masks as flat uint8, `use_*` False: no mask). Pixels masked
    since (in `new`, not in `old`) that are active (seen 1 or 2) leave the integral: with two thresholds their
    OFF count joins `on` (a masked row counts all its events there), seen becomes 3 if `counting` else 0. Pixels
    released since (in `old`, not in `new`) get seen 0 and back[q] True (`back` all False on entry). Returns
    (how many left, how many were released)."""
    gone = 0
    released = 0
    for q in range(seen.size):
        was = use_old and old[q] != 0
        now = use_new and new[q] != 0
        if now and not was:
            s = seen[q]
            if s == 1 or s == 2:
                if two:
                    on[q] += off[q]
                seen[q] = 3 if counting else 0
                gone += 1
        elif was and not now:
            seen[q] = 0
            back[q] = True
            released += 1
    return gone, released


@njit(cache=True, nogil=True)
def lookup_u8(img, lut_b, lut_informative, b, informative):
    """b[q], informative[q] = the tables' entries for the uint8 value img[q] (flat arrays)."""
    for q in range(img.size):
        v = img[q]
        b[q] = lut_b[v]
        informative[q] = lut_informative[v]


@njit(cache=True, nogil=True)
def fall_back_u8(pixels, img, lut_log, lut_u8, log_ref, log_lat, display, deblurred):
    """At the marked pixels (flat bool) of a uint8 frame: both log images get the frame's table entry, both uint8
    images its rendering (all flat)."""
    for q in range(pixels.size):
        if pixels[q]:
            v = img[q]
            log_ref[q] = lut_log[v]
            log_lat[q] = lut_log[v]
            display[q] = lut_u8[v]
            deblurred[q] = lut_u8[v]
