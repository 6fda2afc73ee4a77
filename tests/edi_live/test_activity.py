"""The static-scene policy against sensor noise (edi_live.activity, used by the worker): a simulated still
camera with 0.5 events/s per pixel of background noise and APS frames at 20 fps, through the real worker and
reconstructor in 1 ms packets. Oracles: the simulator's own labels (which events are noise, when motion starts)."""

from __future__ import annotations

import numpy as np

from edi_live.activity import SceneActivity, StaticScene
from edi_live.config import EdiConfig
from edi_live.datatypes import EVENT_DTYPE
from edi_live.node import default_reconstructor
from edi_live.ring import EventRing
from edi_live.worker import EdiWorker
from tools.stream_noise import noisy_scene, onset_delay_us, scene_packets


def test_a_still_noisy_scene_makes_no_frames_and_no_deblurs_beyond_the_first():
    events, frames, _ = noisy_scene(2.0)
    ring = EventRing(capacity_events=1 << 20, capacity_frames=256, policy="wait")
    for p in scene_packets(events, frames):
        ring.push(p)
    ring.close()
    sent = []
    worker = EdiWorker(ring, default_reconstructor(240, 180, EdiConfig()), EdiConfig(every=1000, heartbeat_s=3600),
                       [sent.append])
    worker.start()
    assert worker.done.wait(60) and worker.error is None
    assert len(events) > 30_000  # the noise is really there (0.5 Hz x 43200 pixels x 2 s)
    assert [r.kind for r in sent] == ["deblurred"]  # the first reference; the heartbeat would be the rest
    assert worker.skipped_static_deblur == len(frames) - 1
    assert worker.stats()["noise_only_events"] > 0.9 * len(events)


def test_the_first_frame_after_a_motion_onset_comes_within_one_aps_period():
    # onset_delay_us also checks that nothing but the first deblurred frame came before the onset
    assert onset_delay_us() < 50_000
    assert onset_delay_us(seed_shift=3, every=5000) < 50_000  # a large --every does not delay it


def test_noise_alone_is_quiet_and_an_edge_is_active():
    rng = np.random.default_rng(0)
    act = SceneActivity(240, 180)
    noise = np.zeros(20_000, EVENT_DTYPE)
    noise["t"] = np.sort(rng.integers(0, 1_000_000, noise.size))  # ~0.46 Hz per pixel over 1 s
    noise["x"], noise["y"] = rng.integers(0, 240, noise.size), rng.integers(0, 180, noise.size)
    for k in range(0, noise.size, 20):  # ~1 ms chunks
        assert not any(active for _, active, _ in act.update(noise[k:k + 20]))
    edge = np.zeros(181, noise.dtype)  # a vertical edge crossing one column: every row fires within 1 ms
    edge["t"] = 1_000_000 + np.arange(181) * 5
    edge["t"][-1] = 1_001_000  # a span is judged at the first event after it
    edge["x"][:-1], edge["y"][:-1] = 100, np.arange(180)
    assert act.update(edge) == [(0, False, 1_000_000), (180, True, 1_001_000)] and act.active_since(1_000_000)


def test_verdicts_fall_at_the_same_events_however_the_stream_is_cut():
    # noise, then an edge sweeping the sensor: the verdicts (where they fall, which way) of one call are the oracle
    events, _, onset_us = noisy_scene(1.2, onset_s=1.0)
    whole = SceneActivity(240, 180).update(events)
    assert any(active and at > 0 and events["t"][at] >= onset_us for at, active, _ in whole)  # the motion is seen
    assert not any(active and events["t"][at] < onset_us for at, active, _ in whole)  # and nothing before it
    for size in (1, 97, 5000):
        if size == 1:
            events_used = events[:20_000]  # one event per call: a prefix is enough (and quick)
            want = [v for v in whole if v[0] < len(events_used)]
        else:
            events_used, want = events, whole
        act, got = SceneActivity(240, 180), []
        for lo in range(0, len(events_used), size):
            got += [(lo + at, active, end) for at, active, end in act.update(events_used[lo:lo + size])]
        assert got == want, size


def test_the_kernel_and_its_python_form_agree():
    from edi_live.edi import _backend

    events, _, _ = noisy_scene(1.2, onset_s=1.0)
    kernel = SceneActivity(240, 180).update(events)
    with _backend.numpy_reference():
        reference = SceneActivity(240, 180).update(events)
    assert kernel == reference and any(active for _, active, _ in kernel)


def _reference_verdicts(events, width, height, *, check_us, window_us, max_noise_hz, sigmas, margin, support_us):
    """The windows' rule written out plainly, over the background-activity filter applied to every event."""
    import math

    from edi_live.edi import background_activity_keep, new_activity_map

    supported = background_activity_keep(events, width, height, new_activity_map(width, height), support_us)
    npix, out = width * height, []
    start = end = None
    n = s = 0
    for i, t in enumerate(events["t"].tolist()):
        begin = t // check_us * check_us
        if start is None:
            start, end = begin, begin + check_us
        elif begin >= end:
            pixel_s = npix * (end - start) * 1e-6
            most = max_noise_hz * pixel_s
            p = 1.0 - math.exp(-8.0 * (n / pixel_s) * support_us * 1e-6)
            active = (n > most + sigmas * math.sqrt(most) + margin
                      or s > n * p + sigmas * math.sqrt(n * p * (1.0 - p)) + margin)
            out.append((i, active, end))
            if active or end - start >= window_us:
                start, n, s = begin, 0, 0
            end = begin + check_us
        n += 1
        s += bool(supported[i])
    return out


def test_verdicts_equal_the_rule_over_every_events_neighbour_test():
    """The kernel stops testing neighbours once a window's count alone makes it active: the verdicts must be those
    of the rule applied with every event's neighbour test, on a noisy scene with an edge and on a busy one (the
    demo preset: ~1000 events per ms, where the count decides most windows before their end)."""
    from edi_live.simulation import preset, simulate

    busy = simulate(preset("demo", duration_s=0.3, ground_truth=False)).events
    for events in (noisy_scene(1.2, onset_s=0.4)[0], busy):
        act = SceneActivity(240, 180)
        got = act.update(events)
        want = _reference_verdicts(events, 240, 180, check_us=act.check_us, window_us=act.window_us,
                                   max_noise_hz=act.max_noise_hz, sigmas=act.sigmas, margin=act.margin,
                                   support_us=act.support_us)
        assert [(int(a), bool(b), int(c)) for a, b, c in got] == want
        assert sum(b for _, b, _ in want) > 10
    per_ms = np.bincount((busy["t"] - busy["t"][0]) // 1000)
    assert np.median(per_ms) > 2 * 5.0 * 240 * 180 * 1e-3  # the count alone decides there


def test_verdicts_on_random_events_with_pixels_off_the_sensor_and_empty_reads():
    """Random bursts and quiet stretches (active and noise verdicts), some events off the sensor (counted, never
    supported), read in random parts with empty ones between: the rule written out plainly."""
    rng = np.random.default_rng(5)
    w, h = 30, 20
    t = np.sort(np.concatenate([rng.integers(0, 200_000, 3000), rng.integers(50_000, 60_000, 4000),
                                rng.integers(140_000, 141_000, 1500)]))
    events = np.zeros(t.size, EVENT_DTYPE)
    events["t"] = t
    events["x"] = rng.integers(0, w + 2, t.size)  # about 6 % off the sensor
    events["y"] = rng.integers(0, h, t.size)
    act = SceneActivity(w, h)
    got, pos = [], 0
    for size in rng.integers(0, 700, 100):
        got += [(pos + at, active, end) for at, active, end in act.update(events[pos:pos + size])]
        pos += int(size)
    got += [(pos + at, active, end) for at, active, end in act.update(events[pos:])]
    want = _reference_verdicts(events, w, h, check_us=act.check_us, window_us=act.window_us,
                               max_noise_hz=act.max_noise_hz, sigmas=act.sigmas, margin=act.margin,
                               support_us=act.support_us)
    assert [(int(a), bool(b), int(c)) for a, b, c in got] == want
    assert 0 < sum(b for _, b, _ in want) < len(want)


def test_spans_decided_by_their_count_keep_the_times_later_tests_read():
    """A busy read's spans are decided by their counts before their events are looked at, and their times enter
    the map only within support_us before a span that may be tested. Bursts (decided by the count) each followed
    by 8 events d µs after the burst's last 8 (all at its last time) and beside them, so that their span is active
    exactly when all 8 find those neighbours' time (d <= support_us: 5000 is the edge), read whole and in random
    parts: the rule written out plainly."""
    rng = np.random.default_rng(11)
    w, h = 240, 180
    parts, gaps = [], (2_000, 5_000, 5_001, 8_000) * 3
    for k, d in enumerate(gaps):
        burst = np.zeros(3000, EVENT_DTYPE)  # ~500 events a ms: far above what noise gives
        burst["t"] = np.sort(30_000 * k + rng.integers(0, 6_000, burst.size))
        burst["x"], burst["y"] = rng.integers(0, w - 1, burst.size), rng.integers(0, h, burst.size)
        burst["t"][-8:] = burst["t"][-1]  # the burst's last 8 at one time: all 8 tests hang on it
        late = burst[-8:].copy()
        late["t"] += d
        late["x"] += 1
        parts += [burst, late]
    closing = np.zeros(1, EVENT_DTYPE)  # a span is judged at the first event after it
    closing["t"] = parts[-1]["t"][-1] + 50_000
    events = np.concatenate(parts + [closing])
    act = SceneActivity(w, h)
    want = _reference_verdicts(events, w, h, check_us=act.check_us, window_us=act.window_us,
                               max_noise_hz=act.max_noise_hz, sigmas=act.sigmas, margin=act.margin,
                               support_us=act.support_us)
    t = events["t"]
    sparse = [active for _, active, end in want if np.count_nonzero((t >= end - act.check_us) & (t < end)) <= 8]
    assert sparse.count(True) == 6 and sparse.count(False) == 6  # d <= 5000: active through the neighbour tests
    for sizes in ([len(events)], rng.integers(1, 9_000, 40)):
        act, got, pos = SceneActivity(w, h), [], 0
        for size in list(sizes) + [len(events)]:
            got += [(pos + at, active, end) for at, active, end in act.update(events[pos:pos + int(size)])]
            pos = min(pos + int(size), len(events))
        assert [(int(a), bool(b), int(c)) for a, b, c in got] == want


def test_a_count_exactly_at_the_noise_bound_as_the_rule_rounds_it():
    """The kernel bounded a window's count by max_noise_hz * npix * span * 1e-6, the rule by max_noise_hz * (npix *
    span * 1e-6): on a 32x100 sensor the first is 42.0 and the second 41.99999999999999 for one 1 ms span, so 42
    unsupported events in it were noise to the kernel (the shortcut 'n <= the one-span bound and s <= margin: not
    active') and active to the rule. Its spans' count bound must be the rule's, to the last bit."""
    w, h = 32, 100
    events = np.zeros(43, EVENT_DTYPE)
    events["t"][:42] = np.arange(42) * 20
    events["t"][42] = 100_000  # a span is judged at the first event after it
    events["x"][:42], events["y"][:42] = np.arange(42) % 16 * 2, np.arange(42) // 16 * 2  # no two are neighbours
    act = SceneActivity(w, h)
    want = _reference_verdicts(events, w, h, check_us=act.check_us, window_us=act.window_us,
                               max_noise_hz=act.max_noise_hz, sigmas=act.sigmas, margin=act.margin,
                               support_us=act.support_us)
    assert len(want) == 1  # one verdict, and which way it goes is the rule's rounding
    assert [(int(a), bool(b), int(c)) for a, b, c in act.update(events)] == want


def _reference_states(events, verdicts, hold_us):
    """Per event, written out: active before the first verdict; after it, active while the latest active verdict
    before the event (its span's end) is at most hold_us before the event's time."""
    t = events["t"].tolist()
    states, v, judged, last = [], 0, False, None
    for i, ti in enumerate(t):
        while v < len(verdicts) and verdicts[v][0] <= i:
            judged = True
            if verdicts[v][1]:
                last = verdicts[v][2]
            v += 1
        states.append(not judged or (last is not None and ti <= last + hold_us))
    return states


def test_segments_follow_the_per_event_rule_however_the_stream_is_cut():
    """Busy reads (one active segment each), an onset after noise, and active stretches broken by gaps longer than
    the hold: the segments' labels per event against the rule applied event by event."""
    from edi_live.simulation import preset, simulate

    busy = simulate(preset("demo", duration_s=0.3, ground_truth=False)).events
    noisy = noisy_scene(1.2, onset_s=0.5)[0]
    gappy = busy.copy()
    gappy["t"] += np.where(np.arange(len(busy)) >= len(busy) // 3, 80_000, 0)  # an 80 ms gap, then more
    gappy["t"] += np.where(np.arange(len(busy)) >= 2 * len(busy) // 3, 200_000, 0)
    rng = np.random.default_rng(8)
    for events in (busy, noisy, gappy):
        verdicts = SceneActivity(240, 180).update(events)
        want_state = _reference_states(events, verdicts, 50_000)
        want, before = [], True
        for s in want_state:
            want.append("noise" if not s else "active" if before else "onset")
            before = s
        assert want.count("noise") > (0 if events is not busy else -1) and want.count("active") > 1000
        for cut_every in (500, 23_000, None):
            scene = StaticScene()
            scene.activity = SceneActivity(240, 180)
            got, pos = [], 0
            while pos < len(events):
                size = cut_every or int(rng.integers(1, 3000))
                part = events[pos:pos + size]
                labels = [""] * len(part)
                for lo, hi, label in scene.segments(part):
                    labels[lo:hi] = [label] * (hi - lo)
                got += labels
                pos += len(part)
            assert [lab == "noise" for lab in got] == [lab == "noise" for lab in want]
            # "onset" labels the whole segment that follows noise (within a read): it starts where the rule says
            starts = [i for i, lab in enumerate(got) if lab == "onset" and (i == 0 or got[i - 1] != "onset")]
            assert starts == [i for i, lab in enumerate(want) if lab == "onset"]
            assert scene.noise_only_events == want.count("noise")
