"""drivers.replay_merge: what the merge of a recording's streams says when their timestamps do not fit together."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.replay_merge import merged_packets
from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.errors import RecordingError

T0 = 1_700_000_000_000_000


def _events(t_first: int, n: int) -> np.ndarray:
    events = np.zeros(n, EVENT_DTYPE)
    events["t"] = t_first + np.arange(n)
    return events


def test_a_frame_far_ahead_of_the_events_is_named_not_the_events_after_it(tmp_path):
    """A frame whose exposure end is an hour ahead (one flipped bit of its timestamp) pushed the merge past the
    events not yet read, and the next event packet, in order in the file, was refused as "events out of time
    order": the error blamed the wrong packet. Now it names the frame's timestamp and byte."""
    path = tmp_path / "f.aedat4"
    with Aedat4Writer(path, 64, 48, compression="none") as writer:
        writer.write_events(_events(T0, 1000))
        writer.write_frame(Frame(np.full((48, 64), 9, np.uint8), T0 + 500, T0 + 500 + 3_600_000_000))
        writer.write_events(_events(T0 + 1000, 1000))
    with Aedat4Reader(path) as reader:
        positions = [pos for _, pos, _ in reader.records()]
    delivered = 0
    with pytest.raises(RecordingError) as info:
        for packet in merged_packets(path):
            delivered += len(packet.events)
    message = str(info.value)
    assert delivered == 1000  # the events before the fault
    assert info.value.offset == positions[2] and "out of time order" not in message
    assert f"frame timestamp {T0 + 500 + 3_600_000_000} µs read at byte {positions[1]}" in message
