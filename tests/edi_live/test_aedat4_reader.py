"""The AEDAT4 reader on the three real DAVIS346 recordings, checked against the data README and two oracles
(dv-processing and the `aedat` package)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from tests.helpers.aedat4_oracles import aedat_read, dv_read

from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, Frame

# Facts stated in ../shared/data/real/README.md (measured there with aedat and dv-processing)
README = {
    "emlb_demo-01_davis346.aedat4": dict(
        sha="97ea11518d8b19581774c4a41ac8b87ca78bc66cdfd13d16a312c78891cc1b6c", events=319_512, on=166_736,
        t0=1643243628737093, t1=1643243629248083, frames=13, exposure_us=20_000, imu=510, serial="00000391",
        table_at=3_664_689, triggers={6: 13, 7: 13, 8: 13, 9: 13}),
    "aestream_davis346.aedat4": dict(
        sha="140ed9a82548ec3c3e66baf5948adb8c0f2e22fac6d22344685b0dc26a2584f0", events=117_667, on=72_363,
        t0=1633953690975950, t1=1633953691105949, frames=3, exposure_us=4_773, imu=130, serial="00000104",
        table_at=1_190_063, triggers={6: 3, 7: 4, 8: 4, 9: 4}),
    "evlib_sample_davis346.aedat4": dict(
        sha="f172b20c14ee36e2cddedc4caacc086f2c4fde50d2af016db6b19a4b03320677", events=6_676, on=None,
        t0=None, t1=None, frames=4, exposure_us=500, imu=160, serial="00000002", table_at=None,
        triggers={6: 4, 7: 5, 8: 4, 9: 4}),
}


def _read_all(path):
    out = {"EVTS": [], "FRME": [], "IMUS": [], "TRIG": []}
    with Aedat4Reader(path) as reader:
        info = reader.source_info
        for stream, data in reader:
            out[stream.type].append(data)
        table = reader.data_table()
        time_range = reader.time_range()
        dtp = reader.data_table_position
    return info, out, table, time_range, dtp


@pytest.fixture(scope="module")
def decoded(real_recordings):
    return {name: _read_all(path) for name, path in real_recordings.items()}


@pytest.mark.parametrize("name", list(README))
def test_recording_is_the_documented_one(real_recordings, name):
    digest = hashlib.sha256(real_recordings[name].read_bytes()).hexdigest()
    assert digest == README[name]["sha"]


@pytest.mark.parametrize("name", list(README))
def test_header_gives_camera_and_resolution(decoded, name):
    info = decoded[name][0]
    assert (info.width, info.height) == (346, 260)
    assert info.name == "DAVIS346" and info.serial == README[name]["serial"]
    assert info.label == f"DAVIS346_{README[name]['serial']}" and info.kind == "replay"


@pytest.mark.parametrize("name", list(README))
def test_counts_and_time_range_match_readme(decoded, name):
    _, data, _, _, _ = decoded[name]
    facts = README[name]
    assert all(a.dtype == EVENT_DTYPE for a in data["EVTS"])
    events = np.concatenate(data["EVTS"])  # (numpy's concatenate packs the dtype; fine for counting)
    assert len(events) == facts["events"]
    if facts["on"] is not None:
        assert int(events["p"].sum()) == facts["on"]
        assert (int(events["t"].min()), int(events["t"].max())) == (facts["t0"], facts["t1"])
    assert len(data["FRME"]) == facts["frames"]
    assert sum(len(a) for a in data["IMUS"]) == facts["imu"]
    assert all(a.dtype == TRIGGER_DTYPE for a in data["TRIG"])
    triggers = np.concatenate(data["TRIG"])
    assert dict(zip(*np.unique(triggers["type"], return_counts=True))) == facts["triggers"]


@pytest.mark.parametrize("name", list(README))
def test_frames_have_documented_exposure_window(decoded, name):
    frames = decoded[name][1]["FRME"]
    assert all(isinstance(f, Frame) for f in frames)
    assert {f.exposure_us for f in frames} == {README[name]["exposure_us"]}
    assert all(f.image.shape == (260, 346) and f.image.dtype == np.uint8 for f in frames)
    assert [f.seq for f in frames] == list(range(len(frames)))


def test_older_layout_uses_soe_eoe_not_the_midpoint_timestamp(decoded):
    # README: aestream stores timestamp = midpoint 1633953690978904 = (976518 + 981291) / 2
    first = decoded["aestream_davis346.aedat4"][1]["FRME"][0]
    assert (first.exposure_start_us, first.exposure_end_us) == (1633953690976518, 1633953690981291)
    assert first.mid_exposure_us == 1633953690978904
    assert first.start_us is not None and first.start_us < first.exposure_start_us  # readout start (SOF) kept


def test_newer_layout_has_no_readout_times(decoded):
    frames = decoded["emlb_demo-01_davis346.aedat4"][1]["FRME"]
    assert all(f.start_us is None and f.end_us is None for f in frames)


def _assert_events_equal(packets, t, x, y, p) -> None:
    """Our event packets, concatenated, equal an oracle's t/x/y/p columns exactly."""
    ours = np.concatenate(packets)
    assert np.array_equal(ours["t"], t)
    assert np.array_equal(ours["x"], x) and np.array_equal(ours["y"], y)
    assert np.array_equal(ours["p"], p)


@pytest.mark.parametrize("name", list(README))
def test_events_frames_imu_triggers_equal_dv_processing(decoded, real_recordings, name):
    _, data, _, _, _ = decoded[name]
    oracle = dv_read(real_recordings[name])
    ref = oracle["events"]
    _assert_events_equal(data["EVTS"], ref["timestamp"], ref["x"], ref["y"], ref["polarity"].astype(bool))
    # dv-processing reports Frame.timestamp = SOE and exposure = EOE - SOE for both layouts
    assert [(f.exposure_start_us, f.exposure_us) for f in data["FRME"]] == \
        [(f["t"], f["exposure_us"]) for f in oracle["frames"]]
    assert all(np.array_equal(a.image, b["image"]) for a, b in zip(data["FRME"], oracle["frames"]))
    assert all(a.dtype == IMU_DTYPE for a in data["IMUS"])
    imu = np.concatenate(data["IMUS"])
    assert np.array_equal(imu["t"], oracle["imu"][:, 0].astype(np.int64))
    np.testing.assert_allclose(imu["temperature_c"], oracle["imu"][:, 1], rtol=1e-6)
    np.testing.assert_allclose(imu["gyro_dps"], oracle["imu"][:, 5:8], rtol=1e-6)
    np.testing.assert_allclose(imu["mag_ut"], oracle["imu"][:, 8:11], rtol=1e-6)
    # dv-processing converts accelerations from g to m/s^2 on its accessor only; the raw field is g
    np.testing.assert_allclose(imu["accel_g"], oracle["imu"][:, 2:5], rtol=1e-6)
    triggers = np.concatenate(data["TRIG"])
    assert np.array_equal(triggers["t"], oracle["triggers"][:, 0])
    assert np.array_equal(triggers["type"], oracle["triggers"][:, 1])


@pytest.mark.parametrize("name", list(README))
def test_everything_equals_the_aedat_package(decoded, real_recordings, name):
    _, data, _, _, _ = decoded[name]
    oracle = aedat_read(real_recordings[name])
    ref = oracle["events"]
    _assert_events_equal(data["EVTS"], ref["t"].astype(np.int64), ref["x"], ref["y"], ref["on"])
    for ours_f, ref_f in zip(data["FRME"], oracle["frames"], strict=True):
        assert (ours_f.exposure_start_us, ours_f.exposure_end_us) == (ref_f["exposure_begin_t"],
                                                                      ref_f["exposure_end_t"])
        assert np.array_equal(ours_f.image, ref_f["pixels"])
    imu = np.concatenate(data["IMUS"])
    assert np.array_equal(imu["t"], oracle["imus"]["t"].astype(np.int64))
    np.testing.assert_array_equal(imu["accel_g"][:, 1], oracle["imus"]["accelerometer_y"])
    triggers = np.concatenate(data["TRIG"])
    assert np.array_equal(triggers["type"], oracle["triggers"]["source"].astype(np.int8))


@pytest.mark.parametrize("name", list(README))
def test_data_table(decoded, name):
    _, data, table, time_range, dtp = decoded[name]
    facts = README[name]
    n_packets = sum(len(v) for v in data.values())
    assert table is not None and len(table) == n_packets
    assert np.all(np.diff(table["byte_offset"]) > 0)
    if facts["table_at"] is None:
        # the evlib clip's table lacks NumElements and timestamps: the reader says so instead of inventing (0, 0)
        assert time_range is None and not table["t_end"].any()
    else:
        assert dtp == facts["table_at"]
        assert time_range[0] == facts["t0"]
        events = table[table["stream_id"] == 0]
        assert int(events["num_elements"].sum()) == facts["events"]


def test_reading_twice_gives_the_same_and_events_are_zero_copy(real_recordings):
    with Aedat4Reader(real_recordings["aestream_davis346.aedat4"]) as reader:
        first = [len(e) for e in reader.events()]
        second = [len(e) for e in reader.events()]
        ev = next(iter(reader.events()))
    assert first == second and sum(first) == 117_667
    assert ev.base is not None and not ev.flags.owndata  # a view of the decompressed packet


def test_data_table_position_is_found_through_the_vtable(real_recordings):
    # README: the field sits at byte 54 in DV files and at byte 50 in the re-containerised evlib clip; the reader
    # must find both (it never uses a fixed offset)
    import struct

    from edi_live.aedat4 import schema as S

    for name, where in (("emlb_demo-01_davis346.aedat4", 54), ("evlib_sample_davis346.aedat4", 50)):
        data = real_recordings[name].read_bytes()
        root = S.root_table(data[14:], b"IOHE")
        assert 14 + root.field_pos(S.IOH_DATA_TABLE_POSITION, 8) == where
        with Aedat4Reader(real_recordings[name]) as reader:
            assert reader.data_table_position == struct.unpack_from("<q", data, where)[0] > 0


def test_interleaved_passes_over_one_reader_do_not_disturb_each_other(real_recordings):
    # the two passes are at different file positions (one skips non-event packets), sharing one file handle
    with Aedat4Reader(real_recordings["emlb_demo-01_davis346.aedat4"]) as reader:
        alone = [e.copy() for e in reader.events()]
        fast, full = reader.events(), reader.records()
        from_fast, from_full = [], []
        for stream, _, data in full:
            if stream.type == "EVTS":
                from_full.append(data)
            nxt = next(fast, None)
            if nxt is not None:
                from_fast.append(nxt)
    for got in (from_fast, from_full):
        assert len(got) == len(alone) and all(np.array_equal(a, b) for a, b in zip(got, alone))


def test_stream_ids_need_not_be_contiguous(tmp_path):
    # like tonic's sample (streams 0, 2, 3): rename our triggers stream 1 -> 3 in the XML and in its packets
    import struct

    from edi_live.aedat4 import Aedat4Writer
    from edi_live.datatypes import TRIGGER_DTYPE as TD

    path = tmp_path / "ids.aedat4"
    ev = np.zeros(50, dtype=EVENT_DTYPE)
    ev["t"] = 1_700_000_000_000_000 + np.arange(50)
    trig = np.zeros(2, dtype=TD)
    trig["t"], trig["type"] = ev["t"][[10, 20]], [8, 9]
    with Aedat4Writer(path, 32, 24, frames=False, triggers=True, compression="lz4") as w:
        w.write_events(ev)
        w.write_triggers(trig)
        w.write_events(ev[-1:])
    data = bytearray(path.read_bytes())
    head_end = 18 + struct.unpack_from("<I", data, 14)[0]
    old, new = b'name="1" path="/outInfo/1/"', b'name="3" path="/outInfo/3/"'
    at = data.index(old, 0, head_end)
    data[at:at + len(old)] = new
    pos = head_end
    for _ in range(3):
        sid, size = struct.unpack_from("<ii", data, pos)
        if sid == 1:
            struct.pack_into("<i", data, pos, 3)
        pos += 8 + size
    path.write_bytes(bytes(data))
    with Aedat4Reader(path) as reader:
        assert [(s.id, s.type) for s in reader.streams] == [(0, "EVTS"), (3, "TRIG")]
        got = [(s.id, len(d)) for s, d in reader]
    assert got == [(0, 50), (3, 2), (0, 1)]
