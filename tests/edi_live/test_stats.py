"""Status line and summary: one live line on a TTY, plain lines otherwise; rates from running totals."""

from __future__ import annotations

import io

import pytest

from edi_live.stats import Rates, StatusLine, collect, format_status, format_summary


STATS = {"events_processed": 1000, "frames_out": 10, "c_on": 0.2, "c_off": 0.25, "drops": 3,
         "ring_occupancy": 0.5, "latency_p50_us": 250.0, "latency_p99_us": 900.0}


def test_tty_status_is_redrawn_in_place(monkeypatch):
    from tests.helpers.terminal import Screen

    screen = Screen(200)
    monkeypatch.setenv("COLUMNS", "200")  # the width of the stream's terminal (it has no descriptor to ask)
    line = StatusLine(_ScreenStream(screen), interval_s=0.0)
    for _ in range(3):
        line.maybe_draw(lambda: STATS)
    line.finish()
    rows = screen.text()
    assert len(rows) == 1 and (screen.y, screen.x) == (1, 0)  # one row, and the cursor on the next
    assert "c_on=0.200 c_off=0.250" in rows[0] and "p99 0.90ms" in rows[0] and "drops 3" in rows[0]


def test_plain_status_lines_when_not_a_terminal():
    stream = io.StringIO()
    line = StatusLine(stream, interval_s=0.0)
    line.maybe_draw(lambda: STATS)
    line.maybe_draw(lambda: STATS)
    line.finish()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and all(x.startswith("edi-live: ") for x in lines) and "\r" not in stream.getvalue()


class ClosedPipe(io.StringIO):
    """stderr piped into a reader that went away ('edi-live ... 2>&1 | head -1')."""

    def __init__(self, tty: bool) -> None:
        super().__init__()
        self.tty, self.writes = tty, 0

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> int:
        self.writes += 1
        raise BrokenPipeError(32, "Broken pipe")


def test_a_status_stream_that_went_away_stops_the_status_not_the_run():
    # the error left the node's supervisor loop, which stopped the run part-way: --out kept 244 of 314 frames
    for tty in (False, True):
        stream = ClosedPipe(tty)
        line = StatusLine(stream, interval_s=0.0)
        for _ in range(3):
            line.maybe_draw(lambda: STATS)
        line.finish()
        assert stream.writes == 1  # tried once, then left alone


def test_rates_between_calls():
    clock = iter([0.0, 2.0, 3.0])
    rates = Rates(clock=lambda: next(clock))
    assert rates.update({"events": 1000}) == {"events": 500.0}
    assert rates.update({"events": 1500}) == {"events": 500.0}


def test_status_and_summary_text():
    assert "c=0.200" in format_status({**STATS, "c_off": 0.2})
    summary = format_summary({**STATS, "aps_frames_in": 4, "frames_deblurred": 4, "frames_latent": 6}, 2.0)
    assert "1000 events" in summary and "4 APS frames in" in summary and "10 frames out" in summary


def test_summary_shows_frames_the_writers_had_to_skip():
    # a lossy --out or --record must not look lossless in the end-of-run report
    clean = format_summary({**STATS, "out_frames": 9, "out_late": 0, "record_events": 5, "record_skipped": 0}, 1.0)
    assert "skipped" not in clean.split("skipped: static")[1].split("\n", 1)[1]
    lossy = format_summary({**STATS, "out_frames": 9, "out_late": 2, "record_events": 5, "record_skipped": 3}, 1.0)
    assert "2 arrived too late" in lossy and "3 items skipped" in lossy


def test_summary_says_when_exposures_were_cut_short_by_the_ring():
    # a ring too small for an exposure deblurs from part of its events: not silent
    assert "ring's history" not in format_summary({**STATS, "ring_history_truncated": 0}, 1.0)
    cut = format_summary({**STATS, "ring_history_truncated": 13}, 1.0)
    assert "warning: 13 exposure window(s)" in cut and "--ring-events" in cut


def test_summary_says_when_events_came_without_any_aps_frame():
    # an events-only recording ran to "0 frames out" with exit 0 and no word on why
    none = format_summary({**STATS, "aps_frames_in": 0, "frames_out": 0}, 1.0)
    assert "warning: no APS frame arrived, so none of the 1000 events became a frame" in none
    assert "no APS frame" not in format_summary({**STATS, "aps_frames_in": 2}, 1.0)
    assert "no APS frame" not in format_summary({"events_processed": 0, "aps_frames_in": 0}, 1.0)  # nothing at all


def test_summary_says_when_aps_frames_came_without_any_event():
    # a frames-only recording (no event stream, or an empty one): its APS frames pass through unsharpened
    # (test_worker), which only this line tells apart from a deblurred run
    only = format_summary({"events_processed": 0, "aps_frames_in": 6, "frames_out": 6, "frames_deblurred": 6}, 1.0)
    assert "warning: no event arrived" in only and "went out as they came, not sharpened: 6 of 6" in only
    assert "no event arrived" not in format_summary({**STATS, "aps_frames_in": 2}, 1.0)
    assert "no event arrived" not in format_summary({"events_processed": 0, "aps_frames_in": 0}, 1.0)


def test_summary_says_when_nothing_arrived():
    # an empty recording (a header and no packet) ran to 'done ... 0 frames out' with exit 0 and no word
    assert "warning: nothing arrived from the input" in format_summary({"events_processed": 0, "aps_frames_in": 0},
                                                                       1.0)
    assert "nothing arrived" not in format_summary({**STATS, "aps_frames_in": 0}, 1.0)
    assert "nothing arrived" not in format_summary({"events_processed": 0, "aps_frames_in": 1}, 1.0)


def test_collect_sums_drops_of_every_stage():
    class Ring:
        pushed_events = 5

        def stats(self):
            return {"ring_dropped_events": 2, "ring_dropped_frames": 1, "ring_occupancy": 0.1}

    class Pub:
        def stats(self):
            return {"sent": 7, "dropped": 4, "latency_p50_us": None, "latency_p99_us": None}

    s = collect(ring=Ring(), publisher=Pub())
    assert s["drops"] == 7 and s["frames_sent"] == 7 and s["events_in"] == 5


def test_summary_reports_the_warm_up_on_its_own_line_and_not_in_the_rate():
    summary = format_summary({**STATS, "warm_up_s": 6.5}, 2.0)
    first, rest = summary.split("\n", 1)
    assert "done in 2.00 s" in first and "(500 ev/s)" in first  # 1000 events over the run alone
    assert "compiled or loaded in 6.50 s" in rest
    assert "compiled or loaded" not in format_summary(STATS, 2.0)  # a node that has not run: no such line


def test_camera_values_show_in_the_status_line_and_summary_with_where_they_came_from():
    ideal = format_status(STATS)
    assert "offset" not in ideal and "black" not in ideal  # an ideal camera's line stays short
    s = {**STATS, "black_level_dn": 10.0, "clock_offset_us": 1500, "clock_offset_estimated": True,
         "black_level_estimated": False}
    assert "black 10 DN" in format_status(s) and "offset 1500 µs" in format_status(s)
    summary = format_summary(s, 1.0)
    assert "black level 10 DN," in summary and "clock offset 1500 µs (estimated)" in summary
    started = format_summary({**s, "black_level_estimated": True, "black_level_from_calibration": True,
                              "clock_offset_from_calibration": True}, 1.0)
    assert "black level 10 DN (the saved calibration's, not yet confirmed)" in started
    assert "clock offset 1500 µs (the saved calibration's, not yet confirmed)" in started


def test_summary_accounts_for_aps_frames_a_still_scene_did_not_deblur():
    # "4 APS frames in" with 3 deblurred must say where the fourth went
    summary = format_summary({**STATS, "aps_frames_in": 4, "frames_deblurred": 3, "skipped_static_deblur": 1}, 1.0)
    assert "APS frames not deblurred: 1" in summary


def test_raw_usb_data_lost_is_said_in_the_summary_in_bytes():
    text = format_summary({**STATS, "source_dropped_bytes": 65536, "source_gaps": 2}, 1.0)
    assert "dropped 65536 bytes of raw data" in text and "2 gap(s)" in text
    assert "raw data" not in format_summary(STATS, 1.0)


LONG = {**STATS, "black_level_dn": 3.0, "clock_offset_us": 2803, "noise_hz_p50": 0.116, "noise_hz_p99": 2.45,
        "noisy_pixels": 184, "pred_psnr_db": 34.69, "still_psnr_db": 29.76, "pred_enabled": True}


def _pty_stream(columns: int):
    """A real terminal of `columns` columns: (its reading end, the stream the status line writes to)."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    return master, os.fdopen(slave, "w", encoding="utf-8")


def _drawn(master: int) -> str:
    import os
    import select

    out = b""
    while select.select([master], [], [], 0)[0]:
        out += os.read(master, 65536)
    return out.decode("utf-8")


def _fields(rows: list[str]) -> list[str]:
    """The status fields a block of rows shows, after the two rates (which differ from draw to draw)."""
    return "  ".join(r.rstrip() for r in rows).split("  ")[2:]


def test_the_live_line_fits_the_terminal_so_redraws_do_not_wrap():
    """A line longer than the terminal wraps, and every redraw then left a row behind (an 80-column terminal
    showed one new row per redraw). It is laid out in rows of whole fields instead, each narrower than the
    terminal (whose width is read from the terminal itself), and redrawn in place: an 80-column terminal shows
    every field, the camera values at the end too; a wide one shows one row."""
    import os

    from tests.helpers.terminal import Screen

    fields = format_status(LONG).split("  ")[2:]
    assert len(format_status(LONG)) > 100
    for columns in (60, 80, 200):
        master, stream = _pty_stream(columns)
        try:
            line = StatusLine(stream, interval_s=0.0)
            assert line.tty
            screen = Screen(columns)
            for _ in range(3):
                line.maybe_draw(lambda: LONG)
                screen.write(_drawn(master))
                block = screen.text()
                assert all(len(r) <= columns - 1 for r in block), (columns, block)
                assert _fields(block) == fields[:len(_fields(block))] and len(block) <= 3, block
        finally:
            stream.close()
            os.close(master)
        if columns >= 80:
            assert _fields(block) == fields, block
        assert (len(block) == 1) == (columns == 200)


def test_fields_are_laid_out_whole_and_a_narrow_terminal_still_gets_something():
    from edi_live.live_line import MAX_ROWS, rows

    assert rows("aa bb  cc  dd", 9) == ["aa bb  cc", "dd"]
    assert rows("aa bb  cc  dd", 8) == ["aa bb", "cc  dd"]
    assert rows("aaaaaaaa  bb", 4) == ["aaaa", "bb"]
    assert rows("short", 80) == ["short"]
    assert rows("  ".join("abcdefgh"), 1) == list("abc")[:MAX_ROWS]  # fields beyond MAX_ROWS rows are dropped


class _ScreenStream(io.StringIO):
    """A terminal's stream whose output lands on a model of its screen (tests/helpers/terminal.py); its width
    is COLUMNS (no file descriptor to ask)."""

    def __init__(self, screen) -> None:
        super().__init__()
        self.screen = screen

    def isatty(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self.screen.write(text)
        return len(text)


@pytest.mark.parametrize("reflow", [True, False])
def test_a_resized_terminal_keeps_just_the_status_rows_and_the_summary_starts_below_them(monkeypatch, reflow):
    """Shrinking the window (tmux resize-window -x 50) while the node ran stacked rows: a terminal that re-wraps
    made two rows of the drawn line, '\\r' returned to the second only, and the padding of the old line's length
    wrapped again; widening then joined the leftovers into one row of garbage. One that cuts its rows (xterm)
    got a row of padding, and every later redraw went one row lower."""
    from tests.helpers.terminal import Screen

    screen = Screen(120, reflow=reflow)
    screen.write("edi-live: INFO: publishing\n")
    monkeypatch.setenv("COLUMNS", "120")
    line = StatusLine(_ScreenStream(screen), interval_s=0.0)
    line.maybe_draw(lambda: LONG)
    fields = format_status(LONG).split("  ")[2:]  # after the two rates, which differ from draw to draw
    for columns in (50, 120, 60, 80):
        screen.resize(columns)
        monkeypatch.setenv("COLUMNS", str(columns))
        for _ in range(2):
            line.maybe_draw(lambda: LONG)
        rows = screen.text()
        block = rows[1:]
        assert rows[0] == "edi-live: INFO: publishing" and 1 <= len(block) <= 3, (columns, rows)
        assert all(len(r) <= columns - 1 for r in block) and _fields(block) == fields[:len(_fields(block))], block
        assert columns < 80 or _fields(block) == fields, block  # every field from 80 columns on
    line.finish()
    screen.write("edi-live: done")
    assert screen.text()[1:] == block + ["edi-live: done"]


def test_a_log_message_takes_the_live_lines_place_and_the_line_ends_below_it(monkeypatch):
    """With the cursor waiting at the line's start, a message written over it without erasing would keep the
    rest of the line (and the rows a shrink made of it) beside and below the message."""
    import logging

    from edi_live.live_line import LogHandler
    from tests.helpers.terminal import Screen

    screen = Screen(120)
    stream = _ScreenStream(screen)
    monkeypatch.setenv("COLUMNS", "120")
    line = StatusLine(stream, interval_s=0.0)
    line.maybe_draw(lambda: LONG)
    screen.resize(50)
    monkeypatch.setenv("COLUMNS", "50")
    handler = LogHandler(stream)
    handler.setFormatter(logging.Formatter("edi-live: %(levelname)s: %(message)s"))
    handler.emit(logging.LogRecord("edi_live", logging.INFO, __file__, 1, "SIGINT: stopping", None, None))
    assert screen.text() == ["edi-live: INFO: SIGINT: stopping"]
    line.finish()
    rows = screen.text()
    assert rows[0] == "edi-live: INFO: SIGINT: stopping" and 2 <= len(rows) <= 4, rows
    assert all(len(r) <= 49 for r in rows[1:]) and _fields(rows[1:])[0] == format_status(LONG).split("  ")[2]
    assert (screen.y, screen.x) == (len(rows), 0)


def test_a_terminal_that_says_zero_columns_gets_a_usable_line(monkeypatch):
    """A pty whose size was never set (made by `script`, some CI runners) reports 0 columns: the line was laid
    out one character per row, three rows of single letters."""
    import os

    from tests.helpers.terminal import Screen

    monkeypatch.delenv("COLUMNS", raising=False)
    master, stream = _pty_stream(0)
    try:
        line = StatusLine(stream, interval_s=0.0)
        line.maybe_draw(lambda: STATS)
        screen = Screen(80)
        screen.write(_drawn(master))
    finally:
        stream.close()
        os.close(master)
    rows = screen.text()
    assert len(rows) <= 2 and "drops 3" in " ".join(rows) and all(len(r) <= 79 for r in rows), rows
