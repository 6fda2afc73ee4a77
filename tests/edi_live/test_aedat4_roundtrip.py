"""Round trips with dv-processing as the oracle: dv-processing writes -> we read; we write -> dv-processing and
`aedat` read. The truth is the data fed to the writer, never our own reader's output."""

from __future__ import annotations

import datetime
import warnings

import numpy as np
import pytest
from tests.helpers.aedat4_oracles import aedat_read, dv_read

from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, Frame
from edi_live.errors import RecordingError

T0 = 1_700_000_000_000_000
COMPRESSIONS = ["none", "lz4", "lz4_high", "zstd", "zstd_high"]


def _scene(rng, width, height, n_events=20_000):
    ev = np.zeros(n_events, dtype=EVENT_DTYPE)
    ev["t"] = T0 + np.sort(rng.integers(0, 100_000, n_events))
    ev["x"], ev["y"] = rng.integers(0, width, n_events), rng.integers(0, height, n_events)
    ev["p"] = rng.random(n_events) < 0.5
    frames = [Frame(rng.integers(0, 256, (height, width), dtype=np.uint8), T0 + 5_000, T0 + 25_000),
              Frame(rng.integers(0, 65536, (height, width), dtype=np.uint16), T0 + 45_000, T0 + 46_500)]
    imu = np.zeros(45, dtype=IMU_DTYPE)
    imu["t"] = T0 + 1_000 * np.arange(45)
    imu["temperature_c"] = 30 + rng.random(45)
    imu["accel_g"], imu["gyro_dps"], imu["mag_ut"] = (rng.normal(size=(45, 3)) for _ in range(3))
    triggers = np.zeros(8, dtype=TRIGGER_DTYPE)
    triggers["t"] = T0 + 5_000 * np.arange(8)
    triggers["type"] = [6, 8, 9, 7, 6, 8, 9, 7]
    return ev, frames, imu, triggers


def _write_ours(path, width, height, scene, compression="lz4", **kw):
    ev, frames, imu, triggers = scene
    with Aedat4Writer(path, width, height, imu=True, triggers=True, compression=compression,
                      camera_name="DAVIS346_00000042", **kw) as w:
        w.write_events(ev[:7000])
        w.write_imu(imu[:20])
        w.write_frame(frames[0])
        w.write_triggers(triggers[:4])
        w.write_events(ev[7000:])
        w.write_frame(frames[1])
        w.write_imu(imu[20:])
        w.write_triggers(triggers[4:])


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_we_write_dv_processing_reads(tmp_path, rng, compression):
    scene = _scene(rng, 346, 260)
    ev, frames, imu, triggers = scene
    path = tmp_path / f"ours_{compression}.aedat4"
    _write_ours(path, 346, 260, scene, compression)
    got = dv_read(path)
    assert got["camera"] == "DAVIS346_00000042" and got["resolution"] == (346, 260)
    assert np.array_equal(got["events"]["timestamp"], ev["t"])
    assert np.array_equal(got["events"]["x"], ev["x"]) and np.array_equal(got["events"]["y"], ev["y"])
    assert np.array_equal(got["events"]["polarity"].astype(bool), ev["p"])
    assert [(f["t"], f["exposure_us"]) for f in got["frames"]] == [(T0 + 5_000, 20_000), (T0 + 45_000, 1_500)]
    assert all(np.array_equal(f["image"], g.image) for f, g in zip(got["frames"], frames))
    assert got["frames"][1]["image"].dtype == np.uint16
    assert {f["source"] for f in got["frames"]} == {1}  # FrameSource.SENSOR for APS frames
    assert np.array_equal(got["imu"][:, 0].astype(np.int64), imu["t"])
    np.testing.assert_allclose(got["imu"][:, 5:8], imu["gyro_dps"], rtol=1e-6)
    np.testing.assert_allclose(got["imu"][:, 1], imu["temperature_c"], rtol=1e-6)
    assert np.array_equal(got["triggers"][:, 0], triggers["t"]) and np.array_equal(got["triggers"][:, 1],
                                                                                    triggers["type"])
    # the time range comes from our FileDataTable, so DV tools can seek
    assert got["time_range"] == (int(min(ev["t"][0], imu["t"][0], triggers["t"][0])),
                                 int(max(ev["t"][-1], imu["t"][-1], triggers["t"][-1])))


def test_dv_processing_seeks_with_our_data_table(tmp_path, rng):
    import dv_processing as dv

    scene = _scene(rng, 346, 260)
    ev = scene[0]
    path = tmp_path / "seek.aedat4"
    _write_ours(path, 346, 260, scene)
    rec = dv.io.MonoCameraRecording(str(path))
    lo, hi = T0 + 30_000, T0 + 60_000
    batch = rec.getEventsTimeRange(lo, hi)
    want = ev[(ev["t"] >= lo) & (ev["t"] < hi)]
    assert len(batch) == len(want) and np.array_equal(batch.numpy()["timestamp"], want["t"])
    frames = rec.getFramesTimeRange(T0 + 40_000, T0 + 50_000)
    assert [f.timestamp for f in frames] == [T0 + 45_000]


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_we_write_aedat_package_reads(tmp_path, rng, compression):
    scene = _scene(rng, 240, 180)
    ev, frames, imu, triggers = scene
    path = tmp_path / "ours.aedat4"
    _write_ours(path, 240, 180, scene, compression)
    got = aedat_read(path)
    assert got["streams"][0] == {"type": "events", "width": 240, "height": 180}
    assert np.array_equal(got["events"]["t"].astype(np.int64), ev["t"])
    assert np.array_equal(got["events"]["x"], ev["x"]) and np.array_equal(got["events"]["on"], ev["p"])
    f0, f1 = got["frames"]
    assert (f0["exposure_begin_t"], f0["exposure_end_t"]) == (T0 + 5_000, T0 + 25_000)
    assert np.array_equal(f0["pixels"], frames[0].image) and np.array_equal(f1["pixels"], frames[1].image)
    assert np.array_equal(got["imus"]["t"].astype(np.int64), imu["t"])
    np.testing.assert_array_equal(got["imus"]["magnetometer_z"], imu["mag_ut"][:, 2])
    assert np.array_equal(got["triggers"]["source"], triggers["type"].astype(np.uint8))


def _dv_write(path, compression, rng):
    import dv_processing as dv

    cfg = dv.io.MonoCameraWriter.DAVISConfig("DAVIS346_00000777", (346, 260),
                                             getattr(dv.CompressionType, compression.upper()))
    truth = {}
    with_events = dv.data.generate.uniformEventsWithinTimeRange(T0, datetime.timedelta(milliseconds=80), (346, 260),
                                                                30_000, 7)
    truth["events"] = with_events.numpy().copy()
    img8 = rng.integers(0, 256, (260, 346), dtype=np.uint8)
    img16 = rng.integers(0, 65536, (260, 346), dtype=np.uint16)
    truth["frames"] = [(T0 + 10_000, 2_000, img8), (T0 + 50_000, 700, img16)]
    truth["imu"] = [(T0 + 1_000 * i, 25.0 + i, 0.1 * i, -0.2, 1.0, 3.0, 2.0 * i, -1.0, 0.0, 5.0, 0.5) for i in range(25)]
    truth["triggers"] = [(T0 + 100 * i, (6, 8, 9, 7)[i % 4]) for i in range(12)]
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    writer.writeEvents(with_events)
    for t, exp, img in truth["frames"]:
        writer.writeFrame(dv.Frame(t, exp, 0, 0, img, dv.FrameSource.SENSOR),
                          "frames")
    for s in truth["imu"]:
        writer.writeImu(dv.IMU(*s))
    for t, kind in truth["triggers"]:
        writer.writeTrigger(dv.Trigger(t, dv.TriggerType(kind)))
    del writer  # dv-processing finalises (data table) on destruction
    return truth


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_dv_processing_writes_we_read(tmp_path, rng, compression):
    path = tmp_path / f"dv_{compression}.aedat4"
    truth = _dv_write(path, compression, rng)
    got = {"EVTS": [], "FRME": [], "IMUS": [], "TRIG": []}
    with Aedat4Reader(path) as reader:
        assert reader.compression == compression
        assert reader.source_info.label == "DAVIS346_00000777"
        assert reader.data_table_position > 0
        for stream, data in reader:
            got[stream.type].append(data)
    ev = np.concatenate(got["EVTS"])
    assert np.array_equal(ev["t"], truth["events"]["timestamp"])
    assert np.array_equal(ev["x"], truth["events"]["x"]) and np.array_equal(ev["y"], truth["events"]["y"])
    assert np.array_equal(ev["p"], truth["events"]["polarity"].astype(bool))
    assert [(f.exposure_start_us, f.exposure_us) for f in got["FRME"]] == [(t, e) for t, e, _ in truth["frames"]]
    assert all(np.array_equal(f.image, img) and f.image.dtype == img.dtype
               for f, (_, _, img) in zip(got["FRME"], truth["frames"]))
    imu = np.concatenate(got["IMUS"])
    want = np.array(truth["imu"])
    assert np.array_equal(imu["t"], want[:, 0].astype(np.int64))
    np.testing.assert_allclose(imu["temperature_c"], want[:, 1], rtol=1e-6)
    np.testing.assert_allclose(imu["accel_g"], want[:, 2:5], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(imu["gyro_dps"], want[:, 5:8], rtol=1e-6)
    np.testing.assert_allclose(imu["mag_ut"], want[:, 8:11], rtol=1e-6)
    trig = np.concatenate(got["TRIG"])
    assert [(int(t), int(k)) for t, k in zip(trig["t"], trig["type"])] == truth["triggers"]


def test_unknown_stream_type_is_skipped_with_a_warning(tmp_path, caplog):
    import dv_processing as dv

    path = tmp_path / "bbox.aedat4"
    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DVXplorer_X1", (320, 240))
    cfg.addBoundingBoxStream()
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    events = dv.data.generate.uniformEventsWithinTimeRange(T0, datetime.timedelta(milliseconds=10), (320, 240),
                                                           500, 3)
    writer.writeEvents(events)
    writer.writeBoundingBox(dv.BoundingBox(T0 + 5, 1.0, 2.0, 30.0, 40.0, 0.9, "ball"))
    del writer
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a log line in edi-live's format, never a Python warning
        with caplog.at_level("WARNING", logger="edi_live.aedat4"):
            reader = Aedat4Reader(path)
            with reader:
                got = list(reader)
    notices = [r.getMessage() for r in caplog.records]
    assert len(notices) == 1 and "BBOX" in notices[0] and "skipped" in notices[0]  # once, not per packet
    assert [s.type for s, _ in got] == ["EVTS"] and len(got[0][1]) == 500
    assert (reader.source_info.width, reader.source_info.height) == (320, 240)


def test_reconstruction_frames_for_out(tmp_path, rng):
    # --out: 8-bit frames with timestamp = exposure start = exposure end = latent time, source RECONSTRUCTION
    path = tmp_path / "sharp.aedat4"
    imgs = [rng.integers(0, 256, (180, 240), dtype=np.uint8) for _ in range(3)]
    with Aedat4Writer(path, 240, 180, events=False, frame_source="reconstruction") as w:
        for i, img in enumerate(imgs):
            w.write_frame(Frame(img, T0 + 1000 * i, T0 + 1000 * i))
    got = dv_read(path)
    assert [(f["t"], f["exposure_us"], f["source"]) for f in got["frames"]] == \
        [(T0 + 1000 * i, 0, 5) for i in range(3)]
    assert all(np.array_equal(f["image"], img) for f, img in zip(got["frames"], imgs))
    assert [f["exposure_begin_t"] for f in aedat_read(path)["frames"]] == [T0, T0 + 1000, T0 + 2000]


def test_writer_finalises_after_an_exception(tmp_path, rng):
    ev = _scene(rng, 346, 260)[0]
    path = tmp_path / "crash.aedat4"
    with pytest.raises(ZeroDivisionError):
        with Aedat4Writer(path, 346, 260) as w:
            w.write_events(ev[:1000])
            w.write_events(ev[1000:2000])
            1 / 0
    got = dv_read(path)
    assert np.array_equal(got["events"]["timestamp"], ev["t"][:2000])
    assert got["time_range"][0] == int(ev["t"][0])  # the table was written and dataTablePosition patched
    with Aedat4Reader(path) as reader:
        table = reader.data_table()
    assert len(table) == 2 and list(table["num_elements"]) == [1000, 1000]


def test_writer_rejects_bad_input_without_damaging_the_file(tmp_path, rng):
    ev = _scene(rng, 346, 260)[0]
    path = tmp_path / "strict.aedat4"
    with Aedat4Writer(path, 346, 260) as w:
        w.write_events(ev[1000:2000])
        with pytest.raises(RecordingError, match="backwards"):
            w.write_events(ev[:1000])  # older than what was written
        with pytest.raises(RecordingError, match="not sorted"):
            w.write_events(ev[2000:3000][::-1].copy())
        with pytest.raises(RecordingError, match="EVENT_DTYPE"):
            w.write_events(np.zeros(3, dtype=np.int64))
        with pytest.raises(RecordingError, match="imu"):
            w.write_imu(np.zeros(1, dtype=IMU_DTYPE))  # no IMU stream was requested
    assert np.array_equal(dv_read(path)["events"]["timestamp"], ev["t"][1000:2000])
    with pytest.raises(RecordingError, match="compression"):
        Aedat4Writer(tmp_path / "x.aedat4", 10, 10, compression="gzip")


def test_a_pipe_is_refused_at_open_in_one_line():
    # `--out /dev/stdout | ...` failed at the first packet as "the out-writer thread failed: OSError: [Errno 29]
    # Illegal seek", after part of the run, and left a header-only file
    import os

    read_end, write_end = os.pipe()
    try:
        with pytest.raises(RecordingError, match="pipe or terminal.*give a file name"):
            Aedat4Writer(f"/dev/fd/{write_end}", 64, 48)
    finally:
        os.close(read_end)
        os.close(write_end)


def test_a_named_pipe_is_refused_without_waiting_for_a_reader(tmp_path):
    # `--out FIFO` with nothing reading it blocked in open() for ever; SIGTERM could not end that
    import os
    import threading

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    raised: list[BaseException] = []

    def construct() -> None:
        try:
            Aedat4Writer(fifo, 64, 48)
        except BaseException as exc:  # handed to the test thread
            raised.append(exc)

    worker = threading.Thread(target=construct, daemon=True)  # a daemon: a blocked open cannot hang the run
    worker.start()
    worker.join(30)
    if worker.is_alive():
        with open(fifo, "rb"):  # unblock it, then fail
            pass
        pytest.fail("Aedat4Writer blocked opening a named pipe")
    assert len(raised) == 1 and isinstance(raised[0], RecordingError) and "pipe" in str(raised[0])


def test_recording_cut_off_before_close_still_opens_everywhere(tmp_path, rng):
    # a crash (SIGKILL, power loss) leaves no FileDataTable: the header must then say "no table" (-1), which DV
    # tools treat as an interrupted recording and index by walking the packets
    ev = _scene(rng, 346, 260)[0]
    path, cut = tmp_path / "live.aedat4", tmp_path / "cut.aedat4"
    writer = Aedat4Writer(path, 346, 260)
    writer.write_events(ev[:3000])
    writer.write_events(ev[3000:6000])
    writer.flush()
    cut.write_bytes(path.read_bytes())  # the file as it stands on disk before close()
    writer.close()
    assert np.array_equal(dv_read(cut)["events"]["timestamp"], ev["t"][:6000])
    assert len(aedat_read(cut)["events"]) == 6000
    with Aedat4Reader(cut) as reader:
        assert reader.data_table_position == -1 and sum(len(e) for e in reader.events()) == 6000


def test_colour_and_roi_frames_from_dv_processing(tmp_path, rng):
    import dv_processing as dv

    path = tmp_path / "colour.aedat4"
    bgr = rng.integers(0, 256, (260, 346, 3), dtype=np.uint8)
    bgra = rng.integers(0, 256, (260, 346, 4), dtype=np.uint8)
    patch = rng.integers(0, 256, (10, 12), dtype=np.uint8)
    colour_patch = rng.integers(0, 256, (10, 12, 3), dtype=np.uint8)
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.FrameOnlyConfig("DAVIS346_1", (346, 260)))
    writer.writeFrame(dv.Frame(T0, 1000, 0, 0, bgr, dv.FrameSource.SENSOR), "frames")
    writer.writeFrame(dv.Frame(T0 + 2000, 1000, 0, 0, bgra, dv.FrameSource.SENSOR), "frames")
    writer.writeFrame(dv.Frame(T0 + 5000, 1000, 5, 7, patch, dv.FrameSource.SENSOR), "frames")
    writer.writeFrame(dv.Frame(T0 + 8000, 1000, 5, 7, colour_patch, dv.FrameSource.SENSOR), "frames")
    del writer
    with Aedat4Reader(path) as reader:
        assert reader.source_info.color_filter is None  # demosaiced colour, not a raw mosaic
        colour, no_alpha, roi, colour_roi = [data for _, data in reader]
    assert colour.image.shape == (260, 346, 3) and np.array_equal(colour.image, bgr) and colour.color_filter is None
    assert np.array_equal(no_alpha.image, bgra[..., :3])  # BGRA: alpha dropped, BGR kept
    assert roi.image.shape == (260, 346)  # an ROI frame is placed on the full sensor
    assert np.array_equal(roi.image[7:17, 5:17], patch) and roi.image.sum() == patch.sum()
    assert colour_roi.image.shape == (260, 346, 3) and np.array_equal(colour_roi.image[7:17, 5:17], colour_patch)
