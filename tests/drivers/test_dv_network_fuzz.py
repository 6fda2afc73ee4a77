"""Hostile DV peers, fuzzed with hypothesis: a loopback server sends a valid DV network stream (IOHeader, then
packets) with bytes flipped, cut or appended. The DV input must yield packets of the one event dtype and end with
at most one one-line SourceError; never another exception, a hang or unbounded memory."""

from __future__ import annotations

import struct

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.dv_network import DvNetworkSource
from edi_live.aedat4.writer import events_payloads, info_xml, io_header
from edi_live.datatypes import EVENT_DTYPE
from edi_live.errors import SourceError
from tests.helpers.one_shot_server import serve_once


def _valid_stream() -> bytes:
    header = io_header("none", -1, info_xml([(0, "EVTS", "events")], 32, 24, "DAVIS346_00000001", "none"))[0]
    ev = np.zeros(300, EVENT_DTYPE)
    ev["t"] = 1_700_000_000_000_000 + np.arange(300) * 10
    ev["x"], ev["y"], ev["p"] = np.arange(300) % 32, np.arange(300) % 24, np.arange(300) % 2 == 0
    packets = b"".join(struct.pack("<ii", 0, len(p)) + p for i in range(0, 300, 100)
                       for p, *_ in events_payloads(ev[i:i + 100]))
    return header + packets


VALID = _valid_stream()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(1, 255)), max_size=6),
       st.one_of(st.none(), st.integers(0, len(VALID))), st.binary(max_size=64))
def test_a_mangled_dv_stream_ends_in_packets_and_at_most_one_clear_error(flips, cut, tail):
    data = bytearray(VALID)
    for where, xor in flips:
        data[where] ^= xor
    data = bytes(data[:cut] if cut is not None else data) + tail
    port, server = serve_once(data)
    events = 0
    try:
        with DvNetworkSource([f"tcp://127.0.0.1:{port}"]) as source:
            for packet in source:
                if packet is not None and len(packet.events):
                    assert packet.events.dtype == EVENT_DTYPE
                    events += len(packet.events)
    except SourceError as exc:
        assert "\n" not in str(exc)
    server.join(10)
    assert not server.is_alive()
    assert events <= 300 + len(tail)  # nothing invented beyond what was sent


def test_the_unmangled_stream_delivers_every_event():
    port, server = serve_once(VALID)
    events = []
    try:
        with DvNetworkSource([f"tcp://127.0.0.1:{port}"]) as source:
            for packet in source:
                if packet is not None and len(packet.events):
                    events.append(packet.events)
    except SourceError as exc:  # the peer closing after its last packet is a dropped connection
        assert "\n" not in str(exc)
    server.join(10)
    assert sum(len(e) for e in events) == 300
