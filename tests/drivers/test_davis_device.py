"""DavisSource end to end through pyusb and the emulated camera: recording -> encoder -> emulator -> pyusb ->
reader thread -> decoder reproduces the recording (events exactly, frames within ADC quantisation) for both
chips and all 8 orientation combinations; the configuration written matches libcaer's; any IBackend works."""

from __future__ import annotations

import time

import numpy as np
import pytest
import usb.backend

from drivers.davis import protocol as P
from drivers.davis.device import DavisSource
from drivers.davis.discovery import list_devices
from drivers.emulator import backend
from tests.helpers.recordings import flatten, random_recording

MODELS = {"davis346": (346, 260, False), "davis240": (240, 180, True)}


def _read_all(src, limit_s=30.0):
    out, deadline = [], time.monotonic() + limit_s
    for p in src:
        assert time.monotonic() < deadline, "source did not end"
        if p is not None:
            out.append(p)
    return out


def _check_frames(got, want, x2):
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert a.image.shape == b.image.shape and a.image.dtype == np.uint8
        # ADC quantisation: a DAVIS240's doubled samples keep only even 10-bit values (1 LSB of 8 bits at worst)
        assert np.abs(a.image.astype(int) - b.image.astype(int)).max() <= (1 if x2 else 0)
        assert (a.exposure_start_us, a.exposure_end_us) == (b.exposure_start_us, b.exposure_end_us)


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("orientation", range(8))
def test_round_trip_through_pyusb(rng, model, orientation):
    w, h, x2 = MODELS[model]
    packets = random_recording(rng, w, h, n_events=3000, n_frames=2, n_imu=6)
    be = backend(packets, model=model, speed=0, dvs_orientation=orientation & 4, aps_orientation=orientation)
    with DavisSource(model, backend=be, policy="wait") as src:
        assert (src.info.width, src.info.height, src.info.kind) == (w, h, "emulator")
        out = _read_all(src)
    ev, frames, imu = flatten(out)
    rev, rframes, rimu = flatten(packets)
    assert np.array_equal(ev, rev)
    _check_frames(frames, rframes, x2)
    np.testing.assert_allclose(imu["accel_g"], rimu["accel_g"], atol=1 / 8192)
    np.testing.assert_array_equal(imu["t"], rimu["t"])
    seen = 0
    for p in out:  # ordering contract: a frame only after every event up to its exposure end
        seen += len(p.events)
        for f in p.frames:
            assert not np.any(rev["t"][seen:] <= f.exposure_end_us)


def test_real_recording_matches_replay(real_recordings):
    from drivers.replay import merged_packets

    path = real_recordings["evlib_sample_davis346.aedat4"]
    want = flatten(merged_packets(path))
    for model in ("davis346", "davis240"):
        with DavisSource(model, backend=backend(path, model=model, speed=0), policy="wait") as src:
            got = flatten(_read_all(src))
            assert (src.info.width, src.info.height) == (346, 260)
        assert np.array_equal(got[0], want[0])
        _check_frames(got[1], want[1], model == "davis240")
        assert len(got[2]) == len(want[2])


def test_stop_ends_iteration_promptly():
    src = DavisSource(backend=backend(speed=0))
    with src:
        it = iter(src)
        next(it)
        src.stop()
        t0 = time.monotonic()
        rest = list(it)
    assert time.monotonic() - t0 < 2 and len(rest) <= 1


def test_timestamp_reset_mid_stream_keeps_recording_times(rng):
    packets = random_recording(rng, 346, 260, n_events=4000, n_frames=2, n_imu=0)
    with DavisSource(backend=backend(packets, speed=0, reset_at_us=120_000), policy="wait") as src:
        out = _read_all(src)
        counters = src._decoder.counters
    assert counters["timestamp_resets"] == 1
    assert any(p.gap for p in out) and any(0 in p.triggers["type"] for p in out)
    ev, frames, _ = flatten(out)
    assert np.array_equal(ev, flatten(packets)[0])


# Encoded DAVIS240 bias words, as tabulated in the protocol note §6.2 (computed there from the bit layout)
NOTE_DAVIS240_BIASES = [0x427F, 0x5FFF, 0x400F, 0x5B9B, 0x573B, 0x6DBF, 0x5A4F, 0x690F, 0x23AD, 0x110D, 0x419D,
                        0x65BF, 0x531F, 0x450D, 0x798D, 0x5FFF, 0x5FFF, 0x7D7F, 0x6FDF, 0x5FEF, 0x8410, 0x8410]


def test_configuration_and_start_stop_sequence():
    be = backend(model="davis240", speed=0)
    with DavisSource("davis240", backend=be, exposure_us=5000, frame_interval_us=50000) as src:
        next(iter(src))
    writes = be.writes
    biases = [(p, v) for m, p, v in writes if m == P.BIAS and p < 128]
    assert biases == list(enumerate(NOTE_DAVIS240_BIASES))
    # exposure/interval in ADC cycles: the emulated DAVIS240 reports a 30 MHz ADC clock, deviation 1000
    assert (P.APS, 12, 150_000) in writes and (P.APS, 13, 1_500_000) in writes
    # the emulated logic reports a background-activity and an ROI filter: BA on at 2 ms, ROI = whole array
    assert {(P.DVS, 31, 1), (P.DVS, 32, 8), (P.DVS, 43, 239), (P.DVS, 44, 179)} <= set(writes)
    assert not any(m == P.DVS and p in (11, 51, 61) for m, p, _ in writes)  # filters it lacks are left alone
    idx = {w: i for i, w in reversed(list(enumerate(writes)))}
    order = [(P.MUX, 3, 1), (P.USB, 0, 1), (P.MUX, 1, 1), (P.MUX, 0, 1), (P.DVS, 3, 1), (P.APS, 4, 1)]
    assert [idx[w] for w in order] == sorted(idx[w] for w in order)
    tail = writes[-10:]  # stop: producers off, then MUX/timestamps/USB/chip off
    assert tail[:2] == [(P.DVS, 3, 0), (P.APS, 4, 0)] and tail[-4:] == [(0, 0, 0), (0, 1, 0), (9, 0, 0), (0, 3, 0)]


class _ForeignBackend(usb.backend.IBackend):
    """A backend that is not ours: forwards only the IBackend methods (no emulator extras)."""

    def __init__(self, inner):
        self._inner = inner

    def __getattribute__(self, name):
        if name.startswith("_") or name not in usb.backend.IBackend.__dict__:
            return object.__getattribute__(self, name)
        return getattr(object.__getattribute__(self, "_inner"), name)


def test_any_ibackend_works_without_emulator_extras():
    foreign = _ForeignBackend(backend(model="davis346", speed=0))
    assert not hasattr(foreign, "edi_live_epoch_us")
    before_us = time.time_ns() // 1000
    with DavisSource("auto", backend=foreign) as src:
        assert (src.info.kind, src.info.name, src.info.width) == ("usb", "DAVIS346", 346)
        got, deadline = [], time.monotonic() + 10
        for p in src:
            if p is not None and len(p.events):
                got.append(p)
            if len(got) >= 5 or time.monotonic() > deadline:
                src.stop()
    ev = flatten(got)[0]
    assert len(ev) > 0 and np.all(np.diff(ev["t"]) >= 0)
    assert ev["t"][0] >= before_us - 1_000_000  # device time anchored to the host clock (Unix µs)


def test_generated_scene_with_no_arguments_streams_everything():
    be = backend()
    assert isinstance(be, usb.backend.IBackend)
    with DavisSource(backend=be) as src:
        got, deadline = [], time.monotonic() + 10
        for p in src:
            if p is not None:
                got.append(p)
            ev, frames, imu = flatten(got)
            if (len(frames) >= 2 and len(imu) and len(ev)) or time.monotonic() > deadline:
                src.stop()
    ev, frames, imu = flatten(got)
    assert len(frames) >= 2 and len(imu) > 0 and len(ev) > 0
    assert frames[0].image.shape == (180, 240)
    # the simulator's scene comes through the USB words intact: the frame is what the package renders
    from edi_live.simulation.stream import generated_scene
    sent = next(f for p in generated_scene(240, 180, epoch_us=0) for f in p.frames)
    np.testing.assert_array_equal(frames[0].image, sent.image)
    np.testing.assert_allclose(imu["accel_g"][0], [0, -1, 0], atol=1e-3)


def test_listing_and_serial_selection():
    be = backend(model="davis346", speed=0, serial="SN42")
    (d,) = list_devices(be)
    assert (d.model, d.serial, d.product_id, d.firmware_version) == ("davis346", "SN42", 0x841A, 6)
    with DavisSource(serial="SN42", backend=be) as src:
        assert src.info.serial == "SN42" and src.info.label == "DAVIS346_SN42"


def test_external_input_triggers_round_trip():
    from edi_live.datatypes import EVENT_DTYPE, TRIGGER_DTYPE, Packet

    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = [1000, 2000, 90000], [1, 2, 3], [4, 5, 6]
    tr = np.zeros(3, TRIGGER_DTYPE)
    tr["t"], tr["type"] = [1500, 50000, 60000], [1, 2, 3]  # AEDAT4: rising edge, falling edge, pulse
    rec = [Packet(events=ev, triggers=tr)]
    with DavisSource(backend=backend(rec, speed=0, width=240, height=180), policy="wait") as src:
        out = _read_all(src)
    got = np.concatenate([p.triggers for p in out])
    assert got.tolist() == tr.tolist() and np.array_equal(flatten(out)[0], ev)


def test_decoder_kernel_is_warmed_up_before_the_camera_streams(monkeypatch):
    # The decoder's numba kernel takes up to ~2 s to compile on a cold cache; that must happen before the MUX
    # starts the stream, not on the first USB chunk (a live camera would back up the raw queue meanwhile).
    import drivers.davis.device as device

    be = backend(model="davis240", speed=0)
    seen = {}
    real = device._warm_up_decoder

    def recorder(info):
        seen["writes_before"] = list(be.writes)
        real(info)

    monkeypatch.setattr(device, "_warm_up_decoder", recorder)
    with DavisSource("davis240", backend=be, policy="wait"):
        pass
    assert "writes_before" in seen
    assert not any(w in seen["writes_before"] for w in P.START_MUX_ON)
    assert all(w in be.writes for w in P.START_MUX_ON)
