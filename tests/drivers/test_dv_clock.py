"""drivers.dv_clock: a DV server that starts again with an older clock continues after the earlier times, with one
offset per restart that the camera's streams share."""

from __future__ import annotations

import logging

import numpy as np

from drivers.dv_clock import RESTART_US, DvClock
from edi_live.datatypes import Frame, empty_events


def _events(t0: int, t1: int, n: int = 50) -> np.ndarray:
    ev = empty_events(n)
    ev["t"] = np.linspace(t0, t1, n).astype(np.int64)
    return ev


def _frame(start: int, end: int) -> Frame:
    return Frame(np.zeros((4, 4), np.uint8), start, end, start_us=end, end_us=end + 100)


def test_a_stream_in_order_and_small_disorder_keep_their_times():
    gaps = []
    clock = DvClock(lambda: gaps.append(1))
    for k in range(5):
        ev = _events(10_000 * k, 10_000 * k + 9_000)
        assert clock.events(ev) is ev
    late = _events(40_000 - RESTART_US // 2, 40_000)  # back by less than a restart: the merge's to drop
    assert clock.events(late) is late
    jump = _events(10**9, 10**9 + 5)  # a server with a later clock: time goes on
    assert clock.events(jump) is jump
    assert not gaps and clock.restarts == 0


def test_a_restart_continues_after_the_newest_time_and_every_stream_shares_its_offset():
    gaps = []
    clock = DvClock(lambda: gaps.append(1))
    clock.events(_events(5_000_000, 6_000_000))
    clock.frame(_frame(5_900_000, 5_950_000))
    # the server starts again on the same recording: events first, the frames a little later
    again = clock.events(_events(5_000_000, 5_001_000))
    assert again["t"][0] == 6_000_001 and np.all(np.diff(again["t"]) >= 0)
    offset = int(again["t"][0]) - 5_000_000
    frame = clock.frame(_frame(5_000_200, 5_000_700))
    assert (frame.exposure_start_us, frame.exposure_end_us, frame.start_us, frame.end_us) == (
        5_000_200 + offset, 5_000_700 + offset, 5_000_700 + offset, 5_000_800 + offset)
    imu = np.zeros(2, [("t", "<i8")])
    imu["t"] = [5_001_500, 5_002_000]
    assert list(clock.stamped(imu, "IMUS")["t"]) == [5_001_500 + offset, 5_002_000 + offset]  # a new stream: shifted
    assert clock.restarts == 1 and len(gaps) == 2  # one restart, shown by two streams
    # later packets of the new clock keep the offset; a second restart adds another
    assert clock.events(_events(5_002_000, 5_003_000))["t"][0] == 5_002_000 + offset
    second = clock.events(_events(0, 10))
    assert second["t"][0] == 5_003_000 + offset + 1 and clock.restarts == 2


def test_a_frame_stream_that_shows_the_restart_first_sets_the_offset_for_the_events():
    clock = DvClock()
    clock.events(_events(5_000_000, 6_000_000))
    clock.frame(_frame(5_900_000, 5_950_000))
    frame = clock.frame(_frame(5_000_200, 5_000_700))
    assert frame.exposure_start_us == 6_000_001
    events = clock.events(_events(5_000_300, 5_000_900))
    assert events["t"][0] - 5_000_300 == frame.exposure_start_us - 5_000_200  # the camera's one clock, one offset


def test_a_restart_shown_by_every_stream_is_one_warning_line(caplog):
    # events, frames and IMU of one server served again: one restart, which was said once per stream (three
    # near-identical warnings for one event; the README promises one line)
    clock = DvClock()
    imu = np.zeros(2, [("t", "<i8")])
    imu["t"] = [5_900_000, 5_990_000]
    clock.events(_events(5_000_000, 6_000_000))
    clock.frame(_frame(5_900_000, 5_950_000))
    clock.stamped(imu, "IMUS")
    with caplog.at_level("WARNING", logger="drivers.dv_clock"):
        clock.events(_events(5_000_000, 5_001_000))
        clock.frame(_frame(5_000_200, 5_000_700))
        imu["t"] = [5_000_100, 5_000_900]
        clock.stamped(imu, "IMUS")
        warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert clock.restarts == 1 and len(warned) == 1 and "events stream's clock went back" in warned[0], warned
        clock.events(_events(0, 10))  # a second restart is a second line
        assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 2
