"""What the c policy needs from the stream, gathered per APS frame: each frame's data on a fixed pixel sample (B,
its informative pixels, its level table), the pairs of consecutive frames with the ON/OFF event counts between
their reference times. The policy decides on them afterwards (edi_live.frame_calibration: after the frame left,
once c is estimated).

`step` runs inside the reconstructor's on_frame (the pair and its counts, which that deblur's unreliable-pixel test
needs); `complete` builds the frame's level table later, in settle(), on the thread that runs on_frame (the worker's
or the deblur helper's). The counts between two reference times come from the latent state's accumulator (events
applied since the previous f) corrected by the batch at hand, so that no event is counted twice or missed.
"""

from __future__ import annotations

import collections

import numpy as np

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.c_policy import ContrastPolicy


class ContrastTracker:
    """Frame data and pairs for the estimator; `policy` holds the decision and the current c."""

    def __init__(self, width: int, height: int, policy: ContrastPolicy, *, history_pairs: int,
                 sample_pixels: int) -> None:
        self.width, self.height = width, height
        self.policy = policy
        npix = width * height
        # c is estimated on a fixed random pixel sample: every c evaluation and the tables it needs stay small
        not_sample = np.ones(npix, bool)
        keep = np.random.default_rng(20190616).choice(npix, min(npix, int(sample_pixels)), replace=False)
        not_sample[keep] = False
        self._not_sample = not_sample.reshape(height, width)
        self._prev: contrast.FrameData | None = None
        self._pairs: collections.deque = collections.deque(maxlen=max(1, history_pairs))
        self._todo: tuple | None = None  # what complete() needs to finish the latest frame's data
        self._dropped: contrast.FramePair | None = None  # the pair the latest step pushed out of the history

    @property
    def pairs(self) -> list[contrast.FramePair]:
        return list(self._pairs)

    def mark_gap(self) -> None:
        """Data were lost: the next frame is not paired with the previous one."""
        self._prev = None
        self._pairs.clear()

    def windows_moved(self) -> None:
        """The exposure windows moved (a new clock offset) with this frame: the pairs formed before are dropped, the
        frame just taken, built with the new windows, opens the next pair."""
        self._pairs.clear()

    def restart(self) -> None:
        """The frames' black level changed: pairs formed before are not comparable with the next ones."""
        self.mark_gap()
        self.policy.restart()

    def step(self, events: np.ndarray, b: np.ndarray, informative: np.ndarray, window: tuple[int, int, int],
             hot: np.ndarray | None, acc: tuple[np.ndarray, np.ndarray], t_last: int,
             has_reference: bool, raw: np.ndarray | None = None) -> tuple[contrast.FrameData, contrast.FramePair | None]:
        """This frame's data and the pair with the previous frame. `window` = (ts, te, f); `acc` holds the ON/OFF
        counts applied since the previous f, up to `t_last`, and is the caller's no longer (the pair's counts are
        made from it in place). Returns (this frame's data for the policy, the new
        pair if one was formed). The frame's level table is not built yet: only the policy reads it, so it waits
        for complete() (frame_calibration calls it after the deblurred frame has left, or at once at start-up)."""
        ts, te, f = window
        excluded = self._not_sample if hot is None else (self._not_sample | hot)
        cur = contrast.FrameData(b, informative, None, raw=raw)  # type: ignore[arg-type]  # the table: complete()
        self._todo = (cur, events, window, hot, excluded)
        pair = None
        if self._prev is not None and has_reference:
            n_on, n_off = self._counts_between(events, f, hot, acc, t_last)
            pair = contrast.FramePair(self._prev, cur, n_on, n_off, excluded.reshape(-1))
            if len(self._pairs) == self._pairs.maxlen:  # the pair pushed out is freed in complete(), once the
                self._dropped = self._pairs[0]  # frame has left: returning its count arrays took ~20 µs
            self._pairs.append(pair)
        self._prev = cur
        return cur, pair

    def complete(self) -> None:
        """The level table (on the pixel sample unless the estimator needs the whole image) and event map of the
        frame of the latest step(); a no-op when done. Call before the policy reads that frame or its pairs."""
        self._dropped = None
        if self._todo is None:
            return
        (cur, events, (ts, te, f), hot, excluded), self._todo = self._todo, None
        est = self.policy.estimator
        w, h = self.width, self.height
        if est.needs_full_image:
            cur.table = edi.build_level_table(events, w, h, ts, te, f, mask=hot, segments=est.separate)
            cur.event_map = contrast.event_map(events, w, h, f, ts, te, 0.25 * max(te - ts, 1))
        else:  # the sample's events first (one cheap pass), so the table build touches only them
            sample = edi.events_at_pixels(events, w, h, ~excluded, ts, te)
            cur.table = edi.build_level_table(sample, w, h, ts, te, f, segments=est.separate)

    def _counts_between(self, events: np.ndarray, f: int, hot: np.ndarray | None, acc: tuple[np.ndarray, np.ndarray],
                        t_last: int) -> tuple[np.ndarray, np.ndarray]:
        """ON/OFF counts per pixel from the previous f to this f, without counting any event twice: the
        accumulator holds what was applied after the previous f (up to t_last); this batch may overlap it. The
        counts are `acc`'s arrays, changed in place."""
        n_on, n_off = acc
        t0, t1, sign = _count_range(f, t_last)
        if t1 >= t0:  # floored at 0 where events were taken off (elsewhere the applied counts are >= 0)
            edi.add_counts(events, self.width, self.height, n_on, n_off, t0=t0, t1=t1, mask=hot, sign=sign,
                           floor=True)
        return n_on, n_off


def _count_range(f: int, t_last: int) -> tuple[int, int, int]:
    """(t0, t1, sign): the events with t0 <= t <= t1 to add (sign 1) to or take off (sign -1) the accumulator
    to get the counts from the previous f to f; t1 < t0 when there are none."""
    if f < t_last:  # applied events after this f do not belong to the interval
        return f + 1, t_last, -1
    if f > t_last:  # events up to this f that were not applied yet
        return t_last + 1, f, 1
    return 1, 0, 1
