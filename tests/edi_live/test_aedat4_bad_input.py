"""Damaged AEDAT4 files: one RecordingError naming the file and byte offset, the valid part before the fault still
yielded, never a hang or a foreign exception (also under hypothesis fuzzing of mutated real recordings)."""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.replay import merged_packets
from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.aedat4 import schema as S
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.errors import RecordingError, ResourceError

T0 = 1_700_000_000_000_000


def _packet_offsets(data: bytes) -> list[tuple[int, int, int]]:
    """(header offset, stream id, size) of every packet, walked independently of the reader; stops at the first
    "packet" whose stream id is not a small number (the FileDataTable has no packet header)."""
    n = struct.unpack_from("<I", data, 14)[0]
    out, pos = [], 18 + n
    while pos + 8 <= len(data):
        sid, size = struct.unpack_from("<ii", data, pos)
        if not 0 <= sid < 16 or size <= 0 or pos + 8 + size > len(data):
            break
        out.append((pos, sid, size))
        pos += 8 + size
    return out


def _read(path):
    """Everything the reader yields before it raises: (list of (type, data), error or None)."""
    got = []
    try:
        with Aedat4Reader(path) as reader:
            for stream, data in reader:
                got.append((stream.type, data))
            reader.data_table()
    except RecordingError as exc:
        return got, exc
    return got, None


def _simple_file(path, compression="none", n_packets=5):
    rng = np.random.default_rng(5)
    with Aedat4Writer(path, 64, 48, compression=compression) as w:
        for k in range(n_packets):
            ev = np.zeros(100, dtype=EVENT_DTYPE)
            ev["t"] = T0 + 1000 * k + np.arange(100)
            ev["x"], ev["y"] = rng.integers(0, 64, 100), rng.integers(0, 48, 100)
            w.write_events(ev)
        w.write_frame(Frame(np.full((48, 64), 7, np.uint8), T0 + 10_000, T0 + 12_000))
    return path.read_bytes()


def test_empty_file(tmp_path):
    path = tmp_path / "empty.aedat4"
    path.write_bytes(b"")
    with pytest.raises(RecordingError, match="empty") as info:
        Aedat4Reader(path)
    assert info.value.offset == 0 and str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(RecordingError, match="cannot open"):
        Aedat4Reader(tmp_path / "nope.aedat4")


@pytest.mark.parametrize("content, match", [
    (b"hello world, this is not a recording at all", "not an AEDAT4"),
    (b"#!AER-DAT3.1\r\n#Format: RAW\r\n", "3.1 is not supported"),
    (b"#!AER-DAT4", "truncated"),
    (b"#!AER-DAT4.0\r\n\x10\x00", "truncated"),
])
def test_wrong_magic_or_cut_header(tmp_path, content, match):
    path = tmp_path / "bad.aedat4"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=match) as info:
        Aedat4Reader(path)
    assert str(path) in str(info.value) and "at byte" in str(info.value)


def test_unknown_compression_value(tmp_path):
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path))
    root = S.root_table(bytes(data[14:]), b"IOHE")
    pos = 14 + root.field_pos(S.IOH_COMPRESSION, 4)
    data[pos:pos + 4] = struct.pack("<i", 9)
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="unknown compression type 9") as info:
        Aedat4Reader(path)
    assert info.value.offset == pos


@pytest.mark.parametrize("cut_into", [3, "header"])
def test_truncated_mid_packet_yields_the_packets_before(tmp_path, cut_into):
    path = tmp_path / "f.aedat4"
    data = _simple_file(path, "lz4")
    packets = _packet_offsets(data)
    pos, _, size = packets[3]
    cut = pos + 4 if cut_into == "header" else pos + 8 + size // 2
    path.write_bytes(data[:cut])
    got, err = _read(path)
    assert err is not None and err.offset == pos and "truncated" in str(err)
    assert [len(d) for _, d in got] == [100, 100, 100]  # the three complete packets


def test_truncated_exactly_between_packets(tmp_path):
    path = tmp_path / "f.aedat4"
    data = _simple_file(path, "lz4")
    pos = _packet_offsets(data)[2][0]
    path.write_bytes(data[:pos])
    got, err = _read(path)
    assert len(got) == 2 and err is not None and "FileDataTable" in str(err) and "truncated" in str(err)


def test_file_without_data_table_reads_fully(tmp_path):
    # an interrupted recording: dataTablePosition = -1 and no table at the end
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, "lz4"))
    root = S.root_table(bytes(data[14:]), b"IOHE")
    dtp_pos = 14 + root.field_pos(S.IOH_DATA_TABLE_POSITION, 8)
    dtp = struct.unpack_from("<q", data, dtp_pos)[0]
    data[dtp_pos:dtp_pos + 8] = struct.pack("<q", -1)
    path.write_bytes(bytes(data[:dtp]))
    with Aedat4Reader(path) as reader:
        got = list(reader)
        assert reader.data_table() is None and reader.time_range() is None
    assert [s.type for s, _ in got] == ["EVTS"] * 5 + ["FRME"]


def _size_past_end(data, pos, size):
    data[pos + 4:pos + 8] = struct.pack("<i", 1 << 30)


def _garbage_payload(data, pos, size):
    data[pos + 8:pos + 8 + size] = b"\xff" * size


def _root_offset_outside(data, pos, size):
    data[pos + 8 + 4:pos + 8 + 8] = struct.pack("<I", 0x7FFFFFF0)  # root table offset far outside the packet


def _frame_identifier(data, pos, size):
    data[pos + 16:pos + 20] = b"FRME"


@pytest.mark.parametrize("compression, packet, damage, n_before, message", [
    ("lz4", 1, _size_past_end, 1, "runs past"),
    ("lz4", 2, _garbage_payload, 2, "decompress"),
    ("none", 1, _root_offset_outside, 1, "corrupt EVTS packet"),
    ("none", 0, _frame_identifier, 0, "identifier"),
], ids=["size_past_end_of_file", "bad_compression", "bad_flatbuffer", "wrong_identifier"])
def test_damaged_packet(tmp_path, compression, packet, damage, n_before, message):
    """One damaged packet: the packets before it are yielded, then one error at its header offset."""
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, compression))
    pos, _, size = _packet_offsets(bytes(data))[packet]
    damage(data, pos, size)
    path.write_bytes(bytes(data))
    got, err = _read(path)
    assert len(got) == n_before and err.offset == pos and message in str(err)


def test_frame_with_negative_exposure(tmp_path):
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, "none"))
    pos, sid, size = _packet_offsets(bytes(data))[-1]
    assert sid == 1
    payload = bytes(data[pos + 8:pos + 8 + size])
    eoe = pos + 8 + S.root_table(payload, b"FRME").field_pos(S.FR_EOE, 8)
    data[eoe:eoe + 8] = struct.pack("<q", T0 + 9_000)  # before the exposure start T0 + 10_000
    path.write_bytes(bytes(data))
    got, err = _read(path)
    assert len(got) == 5 and err.offset == pos and "negative exposure" in str(err)


@pytest.mark.parametrize("shape", [(48, 80), (60, 64), (49, 65, 3)])
def test_a_frame_larger_than_the_sensor_is_a_corrupt_packet(tmp_path, shape):
    """A frame the header's sensor cannot hold (here: larger than 64x48) reached the reconstructor, which refused it
    as a usage error (exit 2, "check the source resolution") naming neither the file nor the byte. Now it is damage
    like an event off the sensor: the packets before it, then the error at its packet."""
    path = tmp_path / "f.aedat4"
    with Aedat4Writer(path, 64, 48, compression="none") as w:
        ev = np.zeros(10, dtype=EVENT_DTYPE)
        ev["t"] = T0 + np.arange(10)
        w.write_events(ev)
        w.write_frame(Frame(np.full(shape, 7, np.uint8), T0 + 100, T0 + 200))
    pos = _packet_offsets(path.read_bytes())[-1][0]
    got, err = _read(path)
    assert [kind for kind, _ in got] == ["EVTS"]
    assert err is not None and err.offset == pos and f"{shape[1]}x{shape[0]}" in str(err)
    assert "64x48 sensor" in str(err)


@pytest.mark.parametrize("size", [(32000, 32000), (9000, 260)])
def test_a_header_declaring_a_sensor_no_camera_has_is_refused_before_anything_is_allocated(tmp_path, size):
    """A header naming a 32000x32000 sensor (one damaged digit) made the node allocate ~18 GB of per-pixel state
    before any check; it is now the header's damage, in one line."""
    path = tmp_path / "huge.aedat4"
    with Aedat4Writer(path, *size, compression="none") as w:
        ev = np.zeros(10, dtype=EVENT_DTYPE)
        ev["t"] = T0 + np.arange(10)
        w.write_events(ev)
    with pytest.raises(RecordingError, match=f"{size[0]}x{size[1]} sensor, larger than any event camera") as info:
        Aedat4Reader(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_events_off_the_sensor_are_a_corrupt_packet_in_replay(tmp_path):
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, "none"))
    pos = _packet_offsets(bytes(data))[2][0]
    payload_start = pos + 8
    # first event record of the third packet, found through the general vtable walker
    first, _ = S.root_table(bytes(data[payload_start:]), b"EVTS").vector(0, 16)
    x_at = payload_start + first + 8
    data[x_at:x_at + 2] = struct.pack("<H", 5000)
    path.write_bytes(bytes(data))
    n = 0
    with pytest.raises(RecordingError, match="outside the 64x48 sensor"):
        for packet in merged_packets(path):
            n += len(packet.events)
    assert n >= 100  # what came before the fault was delivered


# ------------------------------------------------------------------------------------------------- fuzzing
def _mutations():
    flips = st.lists(st.tuples(st.integers(0, 10**9), st.integers(1, 255)), min_size=1, max_size=8)
    cut = st.integers(0, 10**9)
    garbage = st.tuples(st.integers(0, 10**9), st.binary(min_size=1, max_size=64))
    return st.one_of(flips.map(lambda f: ("flip", f)), cut.map(lambda c: ("cut", c)),
                     garbage.map(lambda g: ("insert", g)))


def _mutate(data: bytes, mutation) -> bytes:
    kind, arg = mutation
    buf = bytearray(data)
    if kind == "flip":
        for where, xor in arg:
            buf[where % len(buf)] ^= xor
    elif kind == "cut":
        del buf[arg % len(buf):]
    else:
        where, junk = arg
        buf[where % len(buf):where % len(buf)] = junk
    return bytes(buf)


def _read_and_replay(path) -> None:
    """Read and replay a mutated file: each must finish or raise RecordingError; anything else fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _read(path)
        try:
            for _ in merged_packets(path):
                pass
        except RecordingError:
            pass


@pytest.fixture(scope="module")
def small_real(real_recordings):
    return real_recordings["evlib_sample_davis346.aedat4"].read_bytes()


@settings(max_examples=400, deadline=5000, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(mutation=_mutations())
def test_fuzz_reader_and_replay_raise_only_recording_errors(tmp_path, small_real, mutation):
    path = tmp_path / "fuzz.aedat4"
    path.write_bytes(_mutate(small_real, mutation))
    _read_and_replay(path)


@settings(max_examples=25, deadline=10000, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                HealthCheck.too_slow])
@given(mutation=_mutations())
def test_fuzz_aestream_recording(tmp_path, real_recordings, mutation):
    path = tmp_path / "fuzz.aedat4"
    path.write_bytes(_mutate(real_recordings["aestream_davis346.aedat4"].read_bytes(), mutation))
    _read_and_replay(path)


@pytest.fixture(scope="module")
def uncompressed_real(real_recordings, tmp_path_factory):
    """The evlib clip re-encoded without compression, so mutations hit FlatBuffer structure, not LZ4 data."""
    path = tmp_path_factory.mktemp("fuzz") / "plain.aedat4"
    with Aedat4Reader(real_recordings["evlib_sample_davis346.aedat4"]) as reader, \
            Aedat4Writer(path, 346, 260, imu=True, triggers=True, compression="none") as writer:
        put = {"EVTS": writer.write_events, "FRME": writer.write_frame, "IMUS": writer.write_imu,
               "TRIG": writer.write_triggers}
        for stream, data in reader:
            put[stream.type](data)
    return path.read_bytes()


@settings(max_examples=300, deadline=5000, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(mutation=_mutations())
def test_fuzz_uncompressed_flatbuffers(tmp_path, uncompressed_real, mutation):
    path = tmp_path / "fuzz.aedat4"
    path.write_bytes(_mutate(uncompressed_real, mutation))
    _read_and_replay(path)


def test_damaged_data_table_is_reported_after_the_replay(tmp_path):
    """The damage policy (issue 15.6): a damaged FileDataTable is damage like any other. The replay never needs the
    table, so every packet is delivered, and then the RecordingError names the table's byte offset."""
    from drivers.replay import ReplaySource

    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, "lz4"))
    with Aedat4Reader(path) as reader:
        dtp = reader.data_table_position
    data[dtp + 8:] = b"\x00" * (len(data) - dtp - 8)  # wipe the table body after its frame header
    path.write_bytes(bytes(data))
    with Aedat4Reader(path) as reader:
        with pytest.raises(RecordingError, match="FileDataTable") as info:
            reader.data_table()
        assert info.value.offset == dtp
        got = []
        with pytest.raises(RecordingError, match="FileDataTable") as info:
            for events in reader.events():
                got.append(len(events))
        assert sum(got) == 500 and info.value.offset == dtp
    src = ReplaySource(path, speed=0)
    assert src.time_range() is None
    n = 0
    with src, pytest.raises(RecordingError, match="FileDataTable"):
        for packet in src:
            n += len(packet.events) if packet is not None else 0
    assert n == 500


def _no_warnings_read(path) -> tuple[int, RecordingError | None]:
    """Events delivered by merged_packets before it raised, and the error; any Python warning fails the test."""
    n = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            for packet in merged_packets(path):
                n += len(packet.events)
        except RecordingError as exc:
            return n, exc
    return n, None


def test_a_corrupt_stream_id_is_damage_not_a_warning(tmp_path):
    """Issue 15.6: one packet's stream id overwritten with 77 lost its events with only a raw RuntimeWarning and
    exit 0. Now the packets before it are delivered and the error names the file and the packet's byte."""
    path = tmp_path / "f.aedat4"
    data = bytearray(_simple_file(path, "lz4"))
    pos = _packet_offsets(bytes(data))[2][0]
    struct.pack_into("<i", data, pos, 77)
    path.write_bytes(bytes(data))
    n, err = _no_warnings_read(path)
    assert err is not None and err.offset == pos and str(path) in str(err)
    assert "stream 77, which the header does not declare" in str(err)
    assert n == 200  # the two event packets before it


@pytest.mark.parametrize("cut", [1, 7, 40])
def test_a_cut_inside_the_data_table_is_damage(real_recordings, tmp_path, cut):
    """Issue 15.6: a file whose last bytes (inside the FileDataTable) are cut replayed with exit 0 and no word,
    although dv-processing refuses it. Now: every event, then the error at the table's offset."""
    src = real_recordings["evlib_sample_davis346.aedat4"]
    with Aedat4Reader(src) as reader:
        total = sum(len(e) for e in reader.events())
        dtp = reader.data_table_position
    path = tmp_path / "cut.aedat4"
    path.write_bytes(src.read_bytes()[:-cut])
    n, err = _no_warnings_read(path)
    assert n == total
    assert err is not None and err.offset == dtp and "FileDataTable" in str(err)


def test_a_table_that_lists_other_packets_is_damage(tmp_path):
    """A table that parses but disagrees with the packets (here: one packet more in the file than listed)."""
    path = tmp_path / "f.aedat4"
    data = _simple_file(path, "none")
    offsets = _packet_offsets(data)
    first, _, size = offsets[0]
    with Aedat4Reader(path) as reader:
        dtp = reader.data_table_position
    # a copy of the first packet inserted before the table, the header's table position moved along
    patched = bytearray(data[:dtp] + data[first:first + 8 + size] + data[dtp:])
    head = bytes(patched[:18 + struct.unpack_from("<I", patched, 14)[0]])
    at = head.index(struct.pack("<q", dtp))  # the IOHeader's dataTablePosition field
    struct.pack_into("<q", patched, at, dtp + 8 + size)
    path.write_bytes(bytes(patched))
    got, err = _read(path)
    assert len(got) == 7 and err is not None and err.offset == dtp + 8 + size
    assert "lists 6 packets but the file holds 7" in str(err)


@pytest.mark.parametrize("failure", [OSError(24, "Too many open files"), MemoryError()])
def test_running_out_of_files_or_memory_while_decoding_is_not_called_damage(tmp_path, monkeypatch, failure):
    """Under a tight ulimit the decoder's numba cache could not be opened and the replay called the packet corrupt."""
    import edi_live.aedat4.reader as reader

    path = tmp_path / "ok.aedat4"
    events = np.zeros(10, EVENT_DTYPE)
    events["t"] = np.arange(10)
    with Aedat4Writer(path, 8, 8) as writer:
        writer.write_events(events)

    def fail(*args, **kwargs):
        raise failure

    monkeypatch.setattr(reader, "decode_events", fail)
    with pytest.raises(ResourceError, match="a limit of this process, not damage in the file") as caught:
        _read(path)
    assert "corrupt" not in str(caught.value)
