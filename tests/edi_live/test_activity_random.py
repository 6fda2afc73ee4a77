"""Randomised differential test of the activity kernel (edi.activity_verdicts, through SceneActivity): its verdicts
against the rule written out plainly (test_activity._reference_verdicts) for random streams cut into random reads.

The other tests use the default parameters and a few fixed sensors; here the parameters, the sensor (down to 5x3,
with events off it in x and y), the stream (dense bursts that the count alone decides, sparse noise, clusters of
neighbours, events on span boundaries, duplicate times, bursts whose last events are followed by their neighbours
support_us - 1, support_us or support_us + 1 later) and the reads (empty, single events, random, larger than the
stream) all vary by seed."""

from __future__ import annotations

import numpy as np

from edi_live.activity import SceneActivity
from edi_live.datatypes import EVENT_DTYPE
from tests.edi_live.test_activity import _reference_verdicts

_SENSORS = ((30, 20), (8, 6), (240, 180), (32, 100), (5, 3))


def _burst(rng, t, w, h, check_us, support_us):
    n, span = int(rng.integers(50, 3000)), int(rng.integers(1, 6 * check_us))
    ts, xs, ys = t + np.sort(rng.integers(0, span, n)), rng.integers(0, w + 2, n), rng.integers(0, h + 1, n)
    if rng.integers(0, 2):  # its last k at one time, then k events beside them support_us (+-1) later
        k = int(rng.integers(1, 16))
        ts[-k:], xs[-k:] = ts[-1], rng.integers(0, w - 1, k)
        ts = np.concatenate([ts, ts[-k:] + support_us + int(rng.integers(-1, 2))])
        xs, ys = np.concatenate([xs, xs[-k:] + 1]), np.concatenate([ys, ys[-k:]])
    return ts, xs, ys


def _stream(rng, w, h, check_us, support_us):
    parts, t = [], int(rng.integers(0, 3)) * check_us + int(rng.integers(0, 2)) * int(rng.integers(0, check_us))
    for _ in range(int(rng.integers(1, 25))):
        kind = int(rng.integers(0, 5))
        if kind == 0:
            ts, xs, ys = _burst(rng, t, w, h, check_us, support_us)
        elif kind == 1:  # sparse noise
            n = int(rng.integers(1, 60))
            ts = t + np.sort(rng.integers(0, int(rng.integers(1, 20 * check_us)), n))
            xs, ys = rng.integers(0, w + 1, n), rng.integers(0, h, n)
        elif kind == 2:  # a cluster of neighbours
            n = int(rng.integers(2, 80))
            ts = t + np.sort(rng.integers(0, int(rng.integers(1, 3 * check_us)), n))
            xs = np.clip(int(rng.integers(0, w)) + rng.integers(-2, 3, n), 0, w - 1)
            ys = np.clip(int(rng.integers(0, h)) + rng.integers(-2, 3, n), 0, h - 1)
        elif kind == 3:  # on span boundaries and just before them, duplicate times
            n = int(rng.integers(1, 40))
            ts = np.sort((t // check_us + 1 + rng.integers(0, 4, n)) * check_us - rng.integers(0, 2, n))
            xs, ys = rng.integers(0, w, n), rng.integers(0, h, n)
        else:  # a quiet stretch
            t += int(rng.integers(0, 30 * check_us))
            continue
        events = np.zeros(len(ts), EVENT_DTYPE)
        events["t"], events["x"], events["y"] = ts, xs, ys
        parts.append(events)
        t = int(ts.max())
    events = np.concatenate(parts) if parts else np.zeros(1, EVENT_DTYPE)
    return events[np.argsort(events["t"], kind="stable")]


def _read_sizes(rng, n):
    mode, sizes = int(rng.integers(0, 4)), []
    while sum(sizes) < n:
        if mode == 0:
            sizes.append(int(rng.integers(0, 3)))
        elif mode == 1:
            sizes.append(int(rng.integers(0, 200)))
        elif mode == 2:
            sizes.append(int(rng.choice([0, 1, int(rng.integers(1, 5000)), 10**7])))
        else:
            sizes.append(int(rng.integers(0, n + 1)))
    return sizes


def test_verdicts_equal_the_rule_on_random_streams_parameters_and_reads():
    failures = []
    for seed in range(150):
        rng = np.random.default_rng(seed)
        w, h = _SENSORS[seed % len(_SENSORS)]
        params = {}
        if seed % 3 == 1:
            params = dict(check_us=int(rng.integers(1, 3000)), window_us=int(rng.integers(1, 30_000)),
                          support_us=int(rng.integers(0, 10_000)), margin=int(rng.integers(0, 8)),
                          max_noise_hz=float(rng.choice([0.5, 5.0, 50.0, 500.0])),
                          sigmas=float(rng.choice([0.0, 1.0, 5.0])))
        act = SceneActivity(w, h, **params)
        events = _stream(rng, w, h, act.check_us, act.support_us)
        want = _reference_verdicts(events, w, h, check_us=act.check_us, window_us=act.window_us,
                                   max_noise_hz=act.max_noise_hz, sigmas=act.sigmas, margin=act.margin,
                                   support_us=act.support_us)
        for sizes in ([len(events)], _read_sizes(rng, len(events)), _read_sizes(rng, len(events))):
            act, got, pos = SceneActivity(w, h, **params), [], 0
            for size in sizes:
                got += [(pos + at, bool(active), end) for at, active, end in act.update(events[pos:pos + size])]
                pos = min(pos + size, len(events))
            if got != want:
                failures.append((seed, (w, h), params, sizes[:5]))
                break
    assert not failures, failures
