"""The double integral of one exposure accumulated while its events arrive: `RunningDivisor`.

`log_divisor_events` reads all of an exposure's events at once, so a deblurred frame waits for a pass over them
after the exposure ends. Its single-pass kernels keep per-pixel running state, so the same pass can be split: feed
each time-ordered part of the events as it comes, and at exposure end only a finish over the active pixels remains.
Results are bit-identical to log_divisor_events on all the parts at once (the same kernel code runs in the same
order per pixel); the numpy reference keeps the parts and calls log_divisor_events at the finish.
"""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import concat_events
from edi_live.edi import _backend, _kernels_pixels, _kernels_stream
from edi_live.edi.deblur import log_divisor_events
from edi_live.edi.selection import events_at_pixels, time_index, window


class RunningDivisor:
    """log_divisor_events(all events fed, width, height, ts, te, f, c_on, c_off, mask=, event_counts=) in parts.

    feed() takes the stream's events in time order as they come (each once), feed_from() a batch that repeats
    some of them; events outside [ts, te] are skipped. With `event_counts`, every event is counted into it at the
    finish, as log_divisor_events does in one go, and none before: a running divisor dropped unfinished (its
    window was not the exposure's) must leave the counts to the deblur that reads the events instead.
    """

    def __init__(self, width: int, height: int, exposure_start_us: int, exposure_end_us: int, ref_t_us: int | None,
                 c_on: float, c_off: float | None = None, *, mask: np.ndarray | None = None,
                 event_counts: np.ndarray | None = None) -> None:
        self.width, self.height = int(width), int(height)
        self.ts, self.te = int(exposure_start_us), int(exposure_end_us)
        if self.te < self.ts:
            raise ValueError(f"exposure ends before it starts (got {self.ts}..{self.te} µs)")
        self.c_on = float(c_on)
        self.c_off = self.c_on if c_off is None else float(c_off)
        self.f = (self.ts + self.te) // 2 if ref_t_us is None else min(max(int(ref_t_us), self.ts), self.te)
        self.mask, self.event_counts = mask, event_counts
        self.fed_until = -(2**63)  # the time of the last event fed, and how many at that time
        self._at_until = 0
        self.events_fed = 0
        self._parts: list[np.ndarray] | None = None
        self._n_act = 0
        if _backend.have_numba() and 0 < self.te - self.ts < 2**24:
            npix = self.width * self.height
            self._two = self.c_on != self.c_off
            dtype = _kernels_stream.DIVISOR_STATE_TWO if self._two else _kernels_stream.DIVISOR_STATE
            self._state = np.empty(npix, dtype)
            self._seen = np.zeros(npix, np.uint8)
            self._m, self._use_m = _backend.mask_arg(mask)
            self._cnt = _backend.NO_COUNTS if event_counts is None else event_counts
        else:
            self._parts = []

    def matches(self, exposure_start_us: int, exposure_end_us: int, ref_t_us: int, c_on: float, c_off: float,
                mask: np.ndarray | None, event_counts: np.ndarray | None) -> bool:
        """Whether this is the divisor log_divisor_events would compute for these arguments (the same arrays)."""
        return ((self.ts, self.te, self.f, self.c_on, self.c_off) == (int(exposure_start_us), int(exposure_end_us),
                                                                        int(ref_t_us), float(c_on), float(c_off))
                and mask is self.mask and event_counts is self.event_counts)

    def remask(self, mask: np.ndarray | None, events: np.ndarray) -> None:
        """Adopt another mask (pixels flagged or released since the start), as if it had been given from the start:
        pixels masked since leave the integral (their events only counted, as masked ones are), pixels unmasked
        since are integrated from `events`, the time-ordered batch that holds every event fed so far of theirs."""
        if self._parts is not None:  # the reference keeps every event and applies the mask at the finish
            self.mask = mask
            return
        old, use_old = _backend.mask_arg(self.mask)
        self._m, self._use_m = _backend.mask_arg(mask)
        on, off = ("on", "off") if self._two else ("n", "n")  # (one threshold: `n` holds them all)
        back = np.zeros(self.width * self.height, bool)
        # one compiled pass over the pixels (numpy took ~10 passes over the whole image, ~40 µs at 240x180)
        gone, released = _kernels_pixels.remask_divisor(old, use_old, self._m, self._use_m, self._seen,
                                                        self._state[on], self._state[off], self._two,
                                                        self.event_counts is not None, back)
        self._n_act -= gone
        self.mask = mask
        if released:
            t = events["t"]
            lo, hi = time_index(t, self.fed_until, "left"), time_index(t, self.fed_until, "right")
            # one compiled pass over the exposure's events (a numpy gather over them took ~1 ms at 85k events)
            mine = events_at_pixels(events[:lo + min(hi - lo, self._at_until)], self.width, self.height, back,
                                    self.ts, self.te)
            if mine.size:
                fed_before = self.events_fed
                self._feed_window(mine)
                self.events_fed = fed_before  # not new events of the stream

    def feed(self, events: np.ndarray) -> None:
        """The next events of the stream, in time order, none of them fed before."""
        t = events["t"]
        if t.size == 0:
            return
        last = int(t[-1])
        at_last = t.size - time_index(t, last, "left")
        self._at_until = self._at_until + at_last if last == self.fed_until else at_last
        self.fed_until = last
        ev = window(events, self.ts, self.te)
        if ev.size:
            self._feed_window(ev)

    def feed_from(self, events: np.ndarray) -> None:
        """A time-ordered batch that holds every event from some time on, some of them fed already (e.g. all the
        exposure's events at its end): only those after the ones fed so far are fed."""
        t = events["t"]
        lo = time_index(t, self.fed_until, "left")
        hi = time_index(t, self.fed_until, "right")
        self.feed(events[lo + min(hi - lo, self._at_until):])

    def _feed_window(self, ev: np.ndarray) -> None:
        self.events_fed += int(ev.size)
        if self._parts is not None:
            self._parts.append(ev.copy())  # the caller's buffer may be reused
            return
        args = (ev["t"], ev["x"], ev["y"], ev["p"], self.width, self.height, self._m, self._use_m, self.ts, self.f)
        counting = self.event_counts is not None
        if self._two:
            self._n_act += _kernels_stream.divisor_feed_two(*args, self.c_on, self.c_off, self._cnt, counting,
                                                            self._state, self._seen)
        else:
            self._n_act += _kernels_stream.divisor_feed(*args, self.c_on, self._cnt, counting, self._state,
                                                        self._seen)

    def finish(self, counts_after_f: tuple[np.ndarray, np.ndarray] | None = None) \
            -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(active pixels, log D, exponent change f->te or None), as log_divisor_events returns them; with
        `counts_after_f`, the ON/OFF counts of the events in (f, te] are added to them as it does. Call once."""
        if self._parts is not None:
            return log_divisor_events(concat_events(self._parts), self.width, self.height, self.ts, self.te, self.f, self.c_on,
                                      self.c_off, mask=self.mask, event_counts=self.event_counts,
                                      counts_after_f=counts_after_f)
        acc_on, acc_off = counts_after_f if counts_after_f is not None else (_backend.NO_COUNTS, _backend.NO_COUNTS)
        common = (self.width, self.height, self.ts, self.te)
        counting = self.event_counts is not None
        if self._two:
            return _kernels_stream.divisor_finish_two(*common, self.c_on, self.c_off, self._cnt, counting,
                                                      self._state, self._seen, self._n_act, acc_on, acc_off,
                                                      counts_after_f is not None)
        return _kernels_stream.divisor_finish(*common, self.c_on, self._cnt, counting, self._state, self._seen,
                                              self._n_act, acc_on, acc_off, counts_after_f is not None)
