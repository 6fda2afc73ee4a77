"""Event-packet validation: the numba kernels agree with the numpy reference, and the reader's general path (any
layout the combined parse-and-check kernel does not take) gives the same events and the same errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edi_live.aedat4 import Aedat4Reader
from edi_live.aedat4 import _check
from edi_live.aedat4 import decode as decode_mod
from edi_live.aedat4 import schema as S
from edi_live.datatypes import EVENT_DTYPE
from edi_live.errors import RecordingError



def _general_path(monkeypatch) -> None:
    """As if no packet had the plain layout: the Python vtable walk, then the check kernel."""
    monkeypatch.setattr(decode_mod, "parse_check_evts", lambda b, w, h: (-1, 0, -1, 0))


def _evts_payload(raw: np.ndarray) -> bytes:
    """An EVTS FlatBuffer holding these raw 16-byte records as they are (an empty list: no records)."""
    spec = S.TableSpec().vector_bytes(0, raw.tobytes(), raw.size // 16, align=8)
    return S.build_root(b"EVTS", spec)[0]


def _records(t, x, y, p) -> np.ndarray:
    ev = np.zeros(len(t), dtype=EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = t, x, y
    raw = ev.view(np.uint8).reshape(-1, 16).copy()
    raw[:, 12] = p
    return raw.reshape(-1)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.integers(-5, 40), st.sampled_from([2**62, 2**62 + 5, -(2**62), -(2**62) - 1])),
                          st.integers(0, 70), st.integers(0, 50), st.integers(0, 2)), max_size=40))
def test_numba_and_numpy_checks_agree(rows):
    t, x, y, p = (np.array(c, dtype=np.int64) for c in zip(*rows)) if rows else ([], [], [], [])
    raw = _records(t, x, y, p)
    for floor in (-(2**62), 0):
        assert _check.check_events_numpy(raw, 64, 48, floor) == _check.check_events(raw, 64, 48, floor)
    parsed = _check.parse_check_evts(np.frombuffer(_evts_payload(raw), np.uint8), 64, 48)
    assert parsed[2:] == _check.check_events_numpy(raw, 64, 48, -(2**62))


def test_combined_parse_matches_the_general_parser(real_recordings):
    with Aedat4Reader(real_recordings["emlb_demo-01_davis346.aedat4"]) as reader:
        for _, _, payload in reader.packets(("EVTS",)):
            start, count, first, why = _check.parse_check_evts(np.frombuffer(payload, np.uint8), 346, 260)
            assert (start, count) == S.root_table(payload, b"EVTS").vector(0, 16) and (first, why) == (-1, 0)


def test_the_general_path_gives_the_same(real_recordings, monkeypatch, tmp_path):
    path = real_recordings["aestream_davis346.aedat4"]
    with Aedat4Reader(path) as reader:
        fast = [e.copy() for e in reader.events()]
    _general_path(monkeypatch)
    with Aedat4Reader(path) as reader:
        slow = list(reader.events())
    assert len(fast) == len(slow) and all(np.array_equal(a, b) for a, b in zip(fast, slow))
    # and the same error on a bad polarity byte
    bad = tmp_path / "bad.aedat4"
    from edi_live.aedat4 import Aedat4Writer

    ev = np.zeros(10, dtype=EVENT_DTYPE)
    ev["t"] = np.arange(10)
    with Aedat4Writer(bad, 8, 8, compression="none") as w:
        w.write_events(ev)
    data = bytearray(bad.read_bytes())
    first = 18 + int.from_bytes(data[14:18], "little") + 8  # the first packet's payload, after the header
    start, _ = S.root_table(bytes(data[first:]), b"EVTS").vector(0, 16)
    data[first + start + 16 * 3 + 12] = 7
    bad.write_bytes(bytes(data))
    messages = []
    for patched in (False, True):
        if not patched:
            monkeypatch.undo()
        else:
            _general_path(monkeypatch)
        with pytest.raises(RecordingError, match="polarity") as info, Aedat4Reader(bad) as reader:
            list(reader)
        messages.append(str(info.value))
    assert messages[0] == messages[1] and "event 3 of 10" in messages[0]


def test_a_time_beyond_2_62_us_is_refused_by_both_checks_and_the_reader(monkeypatch, tmp_path):
    # the replay keeps 2**62 as "never": events at or past it were dropped without a word (311157 of 319512 read
    # from an emlb copy whose clock was moved there)
    t = np.array([1, 2, 3, 2**62, 2**62 + 1], np.int64)
    raw = _records(t, np.zeros(5), np.zeros(5), np.zeros(5))
    assert _check.check_events_numpy(raw, 8, 8, -(2**62)) == _check.check_events(raw, 8, 8, -(2**62)) == (3, 4)
    low = _records(np.array([-(2**62), 0]), np.zeros(2), np.zeros(2), np.zeros(2))
    assert _check.check_events_numpy(low, 8, 8, -(2**62)) == _check.check_events(low, 8, 8, -(2**62)) == (0, 4)
    from edi_live.aedat4 import Aedat4Writer

    bad = tmp_path / "far.aedat4"
    ev = np.zeros(5, dtype=EVENT_DTYPE)
    ev["t"] = t
    with Aedat4Writer(bad, 8, 8, compression="none") as w:
        w.write_events(ev)
    for patched in (False, True):
        if patched:
            _general_path(monkeypatch)
        with pytest.raises(RecordingError, match=r"event 3 of 5 has a timestamp beyond"), Aedat4Reader(bad) as reader:
            list(reader)
