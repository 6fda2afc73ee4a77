"""Replay: merged_packets' ordering contract on real DV files (dv-processing as the oracle), ReplaySource's Source
behaviour (pacing, loop, stop, None on idle, faults), Pacer arithmetic, the memory bound, and decoding in a
child process."""

from __future__ import annotations

import select
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from drivers.pacing import Pacer
from drivers.replay import ReplaySource, merged_packets
from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, Frame, Packet
from edi_live.errors import ConfigError, RecordingError, SourceError
from edi_live.source import Source

NAMES = ["emlb_demo-01_davis346.aedat4", "aestream_davis346.aedat4", "evlib_sample_davis346.aedat4"]
T0 = 1_700_000_000_000_000


def _dv_oracle(path):
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    events = []
    while (b := rec.getNextEventBatch()) is not None:
        events.append(b.numpy()["timestamp"].copy())
    frames = []
    while (f := rec.getNextFrame()) is not None:
        frames.append((f.timestamp, f.timestamp + int(f.exposure.total_seconds() * 1e6 + 0.5)))
    return np.concatenate(events), frames


@pytest.fixture(scope="module")
def merged(real_recordings):
    return {name: list(merged_packets(real_recordings[name])) for name in NAMES}


@pytest.mark.parametrize("name", NAMES)
def test_merged_events_are_all_events_in_time_order(merged, real_recordings, name):
    packets = merged[name]
    oracle_t, _ = _dv_oracle(real_recordings[name])
    t = np.concatenate([p.events["t"] for p in packets])
    assert np.array_equal(t, oracle_t)  # nothing lost, nothing duplicated, in order
    assert np.all(np.diff(t) >= 0)


@pytest.mark.parametrize("name", NAMES)
def test_frame_comes_after_every_event_of_its_exposure(merged, real_recordings, name):
    packets = merged[name]
    oracle_t, oracle_frames = _dv_oracle(real_recordings[name])
    delivered = 0
    frames = []
    for p in packets:
        delivered += len(p.events)
        for f in p.frames:
            # every event with t <= exposure end is in this packet or an earlier one
            assert delivered >= np.searchsorted(oracle_t, f.exposure_end_us, side="right")
            frames.append((f.exposure_start_us, f.exposure_end_us))
    assert frames == oracle_frames


@pytest.mark.parametrize("name", NAMES)
def test_watermark_promise_holds(merged, name):
    packets = merged[name]
    for i, p in enumerate(packets):
        later = [q.events["t"] for q in packets[i + 1:] if len(q.events)]
        if later:
            assert int(min(a[0] for a in later)) >= p.watermark_us
        if len(p.events):
            assert p.watermark_us > int(p.events["t"][-1])


@pytest.mark.parametrize("name", NAMES)
def test_imu_and_triggers_delivered_in_time_order(merged, real_recordings, name):
    packets = merged[name]
    imu_t = np.concatenate([p.imu["t"] for p in packets])
    trig_t = np.concatenate([p.triggers["t"] for p in packets])
    with Aedat4Reader(real_recordings[name]) as reader:
        n_imu = sum(len(d) for s, d in reader if s.type == "IMUS")
    assert len(imu_t) == n_imu and np.all(np.diff(imu_t) >= 0) and np.all(np.diff(trig_t) >= 0)


def test_aestream_arrival_order_is_undone(merged):
    # the file starts with a trigger packet at ...976518, older events (...975950) follow it
    first = merged["aestream_davis346.aedat4"][0]
    assert int(first.events["t"][0]) == 1633953690975950
    assert len(first.triggers) == 0 or int(first.triggers["t"][0]) >= int(first.events["t"][0])


def test_packets_are_short(merged):
    for p in merged["aestream_davis346.aedat4"]:
        if len(p.events):
            assert int(p.events["t"][-1]) - int(p.events["t"][0]) < 10_000


def test_time_offset_shifts_everything(real_recordings):
    path = real_recordings["evlib_sample_davis346.aedat4"]
    a = list(merged_packets(path))
    b = list(merged_packets(path, time_offset_us=1_000_000))
    ta, tb = (np.concatenate([p.events["t"] for p in x]) for x in (a, b))
    assert np.array_equal(tb, ta + 1_000_000)
    fa = [f.exposure_start_us for p in a for f in p.frames]
    assert [f.exposure_start_us for p in b for f in p.frames] == [t + 1_000_000 for t in fa]


# ---------------------------------------------------------------------------------------------- ReplaySource
def test_replay_source_protocol_and_info(real_recordings):
    src = ReplaySource(real_recordings["emlb_demo-01_davis346.aedat4"], speed=0)
    assert isinstance(src, Source)
    assert (src.info.width, src.info.height, src.info.label, src.info.kind) == (346, 260, "DAVIS346_00000391",
                                                                                "replay")
    with src:
        packets = [p for p in src if p is not None]
    assert sum(len(p.events) for p in packets) == 319_512
    st = src.status()
    assert (st.packets, st.events, st.frames) == (len(packets), 319_512, 13)
    assert [f.seq for p in packets for f in p.frames] == list(range(13))
    assert all(isinstance(p, Packet) and p.arrival_ns > 0 for p in packets)
    assert src.time_range() == (1643243628737093, 1643243629248083)


def test_invalid_speed_is_a_usage_error(real_recordings):
    with pytest.raises(ConfigError, match="speed"):
        ReplaySource(real_recordings["aestream_davis346.aedat4"], speed=-1)


def test_any_resolution_from_the_header(tmp_path):
    for w, h in ((240, 180), (346, 260), (101, 37)):
        path = tmp_path / f"r{w}.aedat4"
        with Aedat4Writer(path, w, h, camera_name="DAVIS240C_00000123") as writer:
            ev = np.zeros(3, dtype=EVENT_DTYPE)
            ev["t"], ev["x"], ev["y"] = T0 + np.arange(3), w - 1, h - 1
            writer.write_events(ev)
        src = ReplaySource(path, speed=0)
        assert (src.info.width, src.info.height, src.info.name, src.info.serial) == (w, h, "DAVIS240C", "00000123")
        with src:
            assert sum(len(p.events) for p in src if p is not None) == 3


def _run_in_thread(fn, timeout_s=20.0):
    result = {}

    def target():
        try:
            result["value"] = fn()
        except BaseException as exc:  # handed to the test thread
            result["error"] = exc

    th = threading.Thread(target=target, daemon=True)
    th.start()
    th.join(timeout_s)
    assert not th.is_alive(), "replay did not end (hang)"
    if "error" in result:
        raise result["error"]
    return result["value"]


@pytest.mark.parametrize("decode_process", [False, True])
def test_idle_yields_none_and_stop_ends_iteration(real_recordings, decode_process):
    # speed 1e-4: the second packet is due hours later, so the source keeps yielding None until stopped
    src = ReplaySource(real_recordings["aestream_davis346.aedat4"], speed=1e-4, poll_s=0.01,
                       decode_process=decode_process)

    def consume():
        seen = []
        with src:
            for p in src:
                if p is not None or seen:  # (a decoding child may need a moment for the first packet)
                    seen.append(p)
                if sum(x is None for x in seen) == 3:
                    threading.Thread(target=src.stop).start()  # stop from another thread
        return seen

    seen = _run_in_thread(consume)
    assert isinstance(seen[0], Packet) and None in seen
    assert seen.count(None) >= 3


@pytest.mark.parametrize("decode_process", [False, True])
def test_loop_keeps_time_monotonic(real_recordings, decode_process):
    path = real_recordings["evlib_sample_davis346.aedat4"]
    src = ReplaySource(path, speed=0, loop=True, decode_process=decode_process)

    def consume():
        packets = []
        with src:
            for p in src:
                if p is None:  # nothing ready yet (allowed by the Source protocol at any speed)
                    continue
                packets.append(p)
                if sum(len(q.events) for q in packets) >= 3 * 6_676:
                    src.stop()
        return packets

    packets = _run_in_thread(consume)
    t = np.concatenate([p.events["t"] for p in packets])
    assert len(t) >= 3 * 6_676 and src.loops >= 2
    assert np.all(np.diff(t) >= 0)
    frames = [f for p in packets for f in p.frames]
    assert all(b.exposure_start_us > a.exposure_start_us for a, b in zip(frames, frames[1:]))
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert len(frames) >= 8


@pytest.mark.parametrize("decode_process", [False, True])
def test_a_looped_recording_of_one_instant_repeats_once_a_millisecond_not_every_microsecond(tmp_path,
                                                                                           decode_process):
    """A recording of a single event looped: each pass one µs after the last made a pass per µs of the replay
    clock, a core kept busy by a paced replay (found by the hardening probe)."""
    from drivers.replay_merge import MIN_PASS_US

    path = tmp_path / "one.aedat4"
    with Aedat4Writer(path, 8, 6) as writer:
        ev = np.zeros(1, dtype=EVENT_DTYPE)
        ev["t"] = T0
        writer.write_events(ev)
    src = ReplaySource(path, speed=0, loop=True, decode_process=decode_process)

    def consume():
        times = []
        with src:
            for p in src:
                if p is not None:
                    times += p.events["t"].tolist()
                    if len(times) >= 4:
                        src.stop()
        return times

    times = _run_in_thread(consume)
    assert np.diff(times[:4]).tolist() == [MIN_PASS_US] * 3


@pytest.mark.parametrize("decode_process", [False, True])
def test_truncated_file_replays_up_to_the_fault_then_raises(tmp_path, real_recordings, decode_process):
    data = real_recordings["aestream_davis346.aedat4"].read_bytes()
    path = tmp_path / "cut.aedat4"
    path.write_bytes(data[: len(data) // 2])
    expected = 0
    with pytest.raises(RecordingError), Aedat4Reader(path) as reader:
        for s, d in reader:
            expected += len(d) if s.type == "EVTS" else 0
    src = ReplaySource(path, speed=0, decode_process=decode_process)

    def consume():
        got = 0
        with src:
            try:
                for p in src:
                    got += len(p.events) if p is not None else 0
            except RecordingError as exc:
                return got, exc
        return got, None

    got, err = _run_in_thread(consume)
    assert err is not None and str(path) in str(err) and "at byte" in str(err)
    assert str(err).count(str(path)) == 1, "the child's message is not prefixed twice"
    assert got == expected > 0


def test_pacer_arithmetic_with_a_fake_clock():
    now = [100.0]
    for speed, expect in ((1.0, 1.0), (4.0, 0.25), (0.5, 2.0)):
        pacer = Pacer(speed, clock=lambda: now[0])
        assert pacer.delay_s(T0) == 0.0  # the first timestamp anchors to now
        assert pacer.delay_s(T0 + 1_000_000) == pytest.approx(expect)
        now[0] += 0.1
        assert pacer.delay_s(T0 + 1_000_000) == pytest.approx(expect - 0.1)
        now[0] = 100.0
    unpaced = Pacer(0, clock=lambda: now[0])
    assert unpaced.delay_s(T0) == 0 and unpaced.delay_s(T0 + 10**9) == 0
    with pytest.raises(ValueError):
        Pacer(float("nan"))


def test_pacer_skips_a_clock_jump_of_years_with_one_warning_and_keeps_real_pauses(caplog):
    """A recording whose clock jumps 5 years ahead replayed at --speed 1 waited those 5 years, showing only '0 ev/s'
    (a pause of a minute or less is the scene's and is kept)."""
    year_us = 365 * 24 * 3600 * 10**6
    now = [100.0]
    pacer = Pacer(1.0, clock=lambda: now[0])
    with caplog.at_level("WARNING"):
        assert pacer.delay_s(T0) == 0.0
        assert pacer.delay_s(T0 + 30_000_000) == pytest.approx(30.0)  # a 30 s pause: waited out
        now[0] += 30.0
        jump = T0 + 30_000_000 + 5 * year_us
        assert pacer.delay_s(jump) <= 0  # due at once, not in 5 years
        assert pacer.delay_s(jump) <= 0  # asked again while waiting: still one jump
        assert pacer.delay_s(jump + 1_000_000) == pytest.approx(1.0)  # pacing goes on from there
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "5.0 years" in warnings[0], warnings


def test_pacer_resumes_at_its_speed_after_a_suspend_instead_of_bursting_the_backlog(caplog):
    """After Ctrl-Z and fg, a paced replay poured out everything it would have shown while stopped, as fast as it
    could; it now goes on at its speed from where it stopped, with one warning. Short lateness (a busy moment)
    is still caught up, so the replay keeps to real time."""
    now = [100.0]
    pacer = Pacer(1.0, clock=lambda: now[0])
    with caplog.at_level("WARNING"):
        assert pacer.delay_s(T0) == 0.0
        now[0] += 0.5  # half a second late: caught up, the schedule stays
        assert pacer.delay_s(T0 + 100_000) == pytest.approx(-0.4)
        now[0] += 30.0  # suspended for 30 s
        assert pacer.delay_s(T0 + 200_000) == 0.0  # due now, not 30 s overdue
        assert pacer.delay_s(T0 + 300_000) == pytest.approx(0.1)  # and the next 100 ms come 100 ms later
        now[0] += 10.0  # again: the second stall is logged at debug level only
        assert pacer.delay_s(T0 + 400_000) == 0.0
        assert pacer.delay_s(T0 + 1_400_000) == pytest.approx(1.0)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "30.3 s behind its schedule, 0.2 s into" in warnings[0], warnings


def test_pacer_says_where_a_stall_fell_in_the_replayed_time_not_across_a_skipped_clock_jump(caplog):
    """The stall warning's '... s into the recording' counted the clock jumps the schedule moved past: a stall 1 s
    after a 5-year jump was '157680002.0 s into the recording'. A jump's first packet is due when the latest one
    was, so 1 s of sensor time was replayed. And a replay whose time starts at 0 always said '0.0 s'."""
    year_us = 365 * 24 * 3600 * 10**6
    now = [100.0]
    pacer = Pacer(1.0, clock=lambda: now[0])
    with caplog.at_level("WARNING"):
        assert pacer.delay_s(T0) == 0.0
        now[0] += 1.0
        jump = T0 + 1_000_000 + 5 * year_us
        assert pacer.delay_s(jump) <= 0  # moved past, with its own warning
        now[0] += 30.0  # then suspended
        assert pacer.delay_s(jump + 1_000_000) == 0.0
    warnings = [r.getMessage() for r in caplog.records if "behind its schedule" in r.getMessage()]
    assert len(warnings) == 1 and "30.0 s behind its schedule, 1.0 s into the replay" in warnings[0], warnings
    with caplog.at_level("WARNING"):
        caplog.clear()
        pacer = Pacer(1.0, clock=lambda: now[0])  # a recording whose time starts at 0 said 0.0 s
        assert pacer.delay_s(0) == 0.0
        now[0] += 30.0
        assert pacer.delay_s(2_000_000) == 0.0
    warnings += [r.getMessage() for r in caplog.records if "behind its schedule" in r.getMessage()]
    assert len(warnings) == 2 and "28.0 s behind its schedule, 2.0 s into the replay" in warnings[1], warnings


def test_a_looped_clock_jump_is_warned_about_a_few_times_not_every_pass(caplog):
    """--loop over a recording with a clock jump warned once per pass: a long loop flooded the log."""
    now = [100.0]
    pacer = Pacer(1.0, clock=lambda: now[0])
    t = T0
    with caplog.at_level("WARNING"):
        for _ in range(20):  # 20 passes, each ending in a 2-minute jump
            pacer.delay_s(t)
            t += 120_000_000
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 3 and "further jumps are not shown" in warnings[-1], warnings


def test_pacer_wait_returns_false_on_timeout_and_on_stop():
    pacer = Pacer(1.0)
    pacer.anchor(T0)
    stop = threading.Event()
    assert pacer.wait(T0 - 5, 0.01, stop) is True  # already due
    assert pacer.wait(T0 + 10_000_000, 0.01, stop) is False  # 10 s away, 10 ms timeout
    stop.set()
    assert pacer.wait(T0 + 10_000_000, 5.0, stop) is False  # returns at once when stopped


# ---------------------------------------------------------------------------------------------- memory bound
def _long_recording(path, n_packets=200, per_packet=10_000, span_us=10_000):
    """n_packets x per_packet events; frames only during the first 0.2 s; an IMU stream declared but empty,
    so both the frame and the IMU stream go silent and must stop holding events back."""
    rng = np.random.default_rng(1)
    base = np.zeros(per_packet, dtype=EVENT_DTYPE)
    base["x"], base["y"] = rng.integers(0, 346, per_packet), rng.integers(0, 260, per_packet)
    base["p"] = rng.random(per_packet) < 0.5
    offsets = np.sort(rng.integers(0, span_us, per_packet))
    with Aedat4Writer(path, 346, 260, imu=True) as w:
        for k in range(n_packets):
            base["t"] = T0 + k * span_us + offsets
            w.write_events(base)
            if k < 20 and k % 4 == 3:
                w.write_frame(Frame(np.zeros((260, 346), np.uint8), T0 + (k - 3) * span_us, T0 + (k - 2) * span_us))
    return n_packets * per_packet


def test_memory_stays_bounded_while_streaming_a_long_file(tmp_path):
    path = tmp_path / "long.aedat4"
    n = _long_recording(path)
    decoded_bytes = n * EVENT_DTYPE.itemsize  # 32 MB if it were all held
    for _ in merged_packets(path, horizon_us=200_000):  # warm up: imports and the numba compile are not data
        break
    tracemalloc.start()
    try:
        count, first_packet_peak = 0, None
        for p in merged_packets(path, horizon_us=200_000):
            count += len(p.events)
            if first_packet_peak is None:
                first_packet_peak = tracemalloc.get_traced_memory()[1]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == n
    # the horizon (0.2 s = 200k events = 3.2 MB) bounds what the merge holds; on top: one 1 MB read chunk, the
    # file buffer and the packet being decoded (without the bound, the whole 32 MB would be held)
    assert peak < 10e6, f"peak {peak / 1e6:.1f} MB for {decoded_bytes / 1e6:.0f} MB of events"
    assert first_packet_peak < 10e6  # output started long before the end of the file


def test_event_cap_bounds_the_merge_when_another_stream_lags(tmp_path):
    # IMU samples only at the start and the end: with a huge horizon, the event cap alone must bound the merge
    path = tmp_path / "lag.aedat4"
    rng = np.random.default_rng(2)
    imu = np.zeros(1, dtype=IMU_DTYPE)
    with Aedat4Writer(path, 64, 64, imu=True) as w:
        imu["t"] = T0
        w.write_imu(imu)
        for k in range(100):
            ev = np.zeros(5_000, dtype=EVENT_DTYPE)
            ev["t"] = T0 + k * 5_000 + np.arange(5_000)
            ev["x"], ev["y"] = rng.integers(0, 64, 5_000), rng.integers(0, 64, 5_000)
            w.write_events(ev)
        imu["t"] = T0 + 10**7
        w.write_imu(imu)
    for _ in merged_packets(path):  # warm up imports and the numba compile
        break

    def peak_bytes(cap):
        tracemalloc.start()
        try:
            n = sum(len(p.events) for p in merged_packets(path, horizon_us=10**9, max_pending_events=cap))
            return n, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    n, capped = peak_bytes(20_000)
    n_all, uncapped = peak_bytes(10**9)
    assert n == n_all == 500_000
    # without the cap every event waits for the last IMU packet: all 8 MB are held at once
    assert uncapped > 8e6 and capped < 4e6, (capped, uncapped)


def test_paced_replay_uses_camera_sized_packets(real_recordings):
    # paced replay hands out 1 ms packets, like a camera's USB transfers; unpaced replay 10 ms ones
    path = real_recordings["aestream_davis346.aedat4"]
    for speed, span_us in ((1000.0, 1_000), (0, 10_000)):
        src = ReplaySource(path, speed=speed)
        packets = _run_in_thread(lambda s=src: [p for p in s if p is not None])
        spans = [int(p.events["t"][-1] - p.events["t"][0]) for p in packets if len(p.events)]
        assert max(spans) < span_us and sum(len(p.events) for p in packets) == 117_667


@pytest.mark.parametrize("span_us", [50, 5_000, 10_000_000])
def test_slot_cuts_match_a_per_event_scan(rng, span_us):
    """Packets are cut where events enter a new max_packet_us slot; the fast search must find exactly the slots
    a plain per-event scan finds (dense, sparse with long gaps, negative times, repeated timestamps)."""
    from drivers.replay_merge import _slot_cuts

    for max_packet_us in (1, 7, 1_000, 10_000):
        t = np.sort(rng.integers(-span_us, span_us, size=int(rng.integers(1, 400)))).astype(np.int64)
        t = np.concatenate([t, t[: len(t) // 4]])
        t.sort()
        expected = []
        for prev, cur in zip(t[:-1].tolist(), t[1:].tolist()):
            if cur // max_packet_us != prev // max_packet_us:
                expected.append(cur // max_packet_us * max_packet_us)
        assert _slot_cuts(t, max_packet_us) == expected


@pytest.mark.parametrize("name", NAMES)
def test_decoding_in_a_child_process_gives_the_same_packets(real_recordings, name):
    def packets(decode_process):
        src = ReplaySource(real_recordings[name], speed=0, decode_process=decode_process)
        with src:
            return [p for p in src if p is not None]

    here, there = _run_in_thread(lambda: (packets(False), packets(True)), timeout_s=60)
    assert len(here) == len(there) > 0
    for a, b in zip(here, there):
        assert a.events.dtype == b.events.dtype == EVENT_DTYPE
        np.testing.assert_array_equal(a.events, b.events)
        np.testing.assert_array_equal(a.imu, b.imu)
        np.testing.assert_array_equal(a.triggers, b.triggers)
        assert a.imu.dtype == b.imu.dtype and a.triggers.dtype == b.triggers.dtype  # (empty ones travel as None)
        assert a.watermark_us == b.watermark_us and not b.gap
        assert [(f.seq, f.exposure_start_us, f.exposure_end_us) for f in a.frames] == \
               [(f.seq, f.exposure_start_us, f.exposure_end_us) for f in b.frames]
        for fa, fb in zip(a.frames, b.frames):
            np.testing.assert_array_equal(fa.image, fb.image)


@pytest.mark.parametrize("packet_us", [1_000, 100_000])
def test_a_killed_decoding_process_is_one_clear_error(real_recordings, packet_us):
    from drivers.decoding_child import DecodeProcess

    # 100 ms packets are larger than the socket's buffer: the child dies in the middle of writing one
    child = DecodeProcess(str(real_recordings["emlb_demo-01_davis346.aedat4"]), packet_us, loop=True)
    try:
        assert select.select([child._sock], [], [], 30.0)[0], "the child sent nothing"
        child._proc.kill()
        with pytest.raises(SourceError, match="decoding process ended unexpectedly"):
            for _ in range(100_000):  # what was already in the pipe, then the error
                child.next_packet(5.0)
    finally:
        child.close()
    assert not child._proc.is_alive()


def test_stopping_mid_file_ends_the_decoding_process(real_recordings):
    src = ReplaySource(real_recordings["emlb_demo-01_davis346.aedat4"], speed=0, loop=True, decode_process=True)

    def consume():
        with src:
            for i, p in enumerate(src):
                if i == 5:
                    src.stop()
        return i

    assert _run_in_thread(consume) >= 5
    import multiprocessing

    deadline = time.monotonic() + 5
    while any(c.name == "edi-live-decode" for c in multiprocessing.active_children()):
        assert time.monotonic() < deadline, "the decoding process outlived the replay"
        time.sleep(0.05)


@pytest.mark.parametrize("failure", [OSError(11, "Resource temporarily unavailable"), EOFError("unexpected EOF")])
def test_decoding_falls_back_to_this_process_when_no_child_can_start(real_recordings, monkeypatch, failure):
    import drivers.decoding_child

    def refuse(*args, **kwargs):  # what Process.start raises: OSError, or EOFError from a forkserver that failed
        raise failure

    monkeypatch.setattr(drivers.decoding_child, "DecodeProcess", refuse)
    path = real_recordings["evlib_sample_davis346.aedat4"]
    with pytest.warns(RuntimeWarning, match="cannot start the decoding process"):
        with ReplaySource(path, speed=0, decode_process=True) as src:
            got = sum(len(p.events) for p in src if p is not None)
    assert got == 6_676


def test_too_few_file_descriptors_decode_in_this_process_without_a_forkserver_traceback(real_recordings):
    """Under 'ulimit -n 14' multiprocessing's forkserver failed receiving the child's descriptors and printed its own
    traceback before the replay fell back; now the replay checks first and says why in its warning."""
    import resource
    import subprocess
    import sys

    path = real_recordings["evlib_sample_davis346.aedat4"]
    code = ("import warnings; from drivers.replay import ReplaySource\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            f"    with ReplaySource({str(path)!r}, speed=0, decode_process=True) as src:\n"
            "        n = sum(len(p.events) for p in src if p is not None)\n"
            "print(n, [str(x.message) for x in w])\n")

    def few_files() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (14, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))

    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          preexec_fn=few_files, cwd=str(Path(__file__).resolve().parents[2]))
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert done.stdout.startswith("6676 ") and "file descriptors free" in done.stdout, done.stdout


def test_a_file_gone_before_the_child_opens_it_is_one_clear_error(tmp_path):
    """The child's own errors (here: the file vanished after the replay was set up) reach the parent as the same
    one-line RecordingError the in-process decoder gives, not as a silent end of the replay."""
    from drivers import decoding_child

    child = decoding_child.DecodeProcess(str(tmp_path / "gone.aedat4"), 1_000, loop=False)
    try:
        with pytest.raises(RecordingError, match=r"gone\.aedat4: cannot open the recording"):
            child.next_packet(30.0)
    finally:
        child.close()


def test_the_forkserver_warm_up_really_decodes_and_leaves_nothing_behind(tmp_path, monkeypatch):
    """The forkserver only logs a failed warm-up (it costs start-up time, not data), so the warm-up's work is
    checked here directly: it must write, decode and delete a recording with the current codec."""
    import tempfile

    from drivers import decoding_child

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    decoding_child.warm_decoder()  # raises if the writer or the reader no longer fit it
    assert list(tmp_path.iterdir()) == []


def test_a_failed_warm_up_is_our_error_and_the_forkserver_logs_it(tmp_path, monkeypatch, caplog):
    import tempfile

    from drivers import decoding_child

    def broken(path, **kwargs):
        raise RecordingError("the codec changed", path, 0)

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(decoding_child, "merged_packets", broken)
    with pytest.raises(SourceError, match="warming up the AEDAT4 decoder failed: RecordingError: .*codec changed"):
        decoding_child.warm_decoder()
    assert list(tmp_path.iterdir()) == []
    with caplog.at_level("WARNING", logger="drivers.decoding_child"):
        assert decoding_child.warm_decoder_or_warn() is False
    assert "warming up the AEDAT4 decoder failed" in caplog.text and "first packet" in caplog.text


def test_a_frame_back_in_time_is_an_error_after_the_frames_before_it(tmp_path, monkeypatch):
    # a frame stamped 10 s in the past became EDI's newest reference, was counted as a "static" skip, and the
    # latent frames after it were built on it: now one error at that frame, the frames before it delivered
    monkeypatch.setattr(Aedat4Writer, "_check", lambda *a, **k: None)  # the writer itself refuses such a file
    path = tmp_path / "back.aedat4"
    t0 = 1_700_000_000_000_000
    starts = [t0 + 10_000, t0 + 30_000, t0 + 30_000 - 10_000_000, t0 + 50_000]
    with Aedat4Writer(path, 32, 24) as writer:
        for k, start in enumerate(starts):
            ev = np.zeros(10, EVENT_DTYPE)
            ev["t"] = t0 + 20_000 * k + np.arange(10)
            writer.write_events(ev)
            writer.write_frame(Frame(np.full((24, 32), 50, np.uint8), start, start + 5_000))
    got = []
    with pytest.raises(RecordingError, match="frames out of time order") as info:
        for packet in merged_packets(str(path)):
            got.extend(f.exposure_start_us for f in packet.frames)
    assert got == starts[:2] and "at byte" in str(info.value)


def _small_recording(path, w, h, n_packets=3):
    rng = np.random.default_rng(7)
    with Aedat4Writer(path, w, h) as writer:
        for k in range(n_packets):
            ev = np.zeros(100, dtype=EVENT_DTYPE)
            ev["t"] = T0 + k * 10_000 + np.arange(100) * 10
            ev["x"], ev["y"] = rng.integers(0, w, 100), rng.integers(0, h, 100)
            writer.write_events(ev)
            writer.write_frame(Frame(np.zeros((h, w), np.uint8), T0 + k * 10_000, T0 + k * 10_000 + 500, seq=k))


@pytest.mark.parametrize("decode_process", [False, True])
def test_a_recording_replaced_by_one_of_another_sensor_size_is_named_not_fed_on(tmp_path, decode_process):
    """Every --loop pass opens the file by its name: one replaced meanwhile (a script recording it again) by a
    recording of another sensor went on into the node, whose reconstructor then stopped on "APS frame is 240x180
    but the reconstructor was set up for 346x260; check the source resolution" (exit 2, a usage error)."""
    path = tmp_path / "rec.aedat4"
    _small_recording(path, 64, 48)
    src = ReplaySource(path, speed=0, loop=True, decode_process=decode_process)
    other = tmp_path / "other.aedat4"
    _small_recording(other, 32, 24)
    other.replace(path)  # before the first pass opens it: the same as between two passes, without a race
    with src, pytest.raises(RecordingError) as info:
        _run_in_thread(lambda: [p for p in src if p is not None])
    message = str(info.value)
    assert "32x24" in message and "64x48" in message and str(path) in message
