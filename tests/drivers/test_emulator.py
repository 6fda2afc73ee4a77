"""The emulated camera itself: the CLI hook spelling, register protocol packing, looping, listing with faults,
and the udev helper it points users to."""

from __future__ import annotations

import importlib
import struct
import time
from array import array

import numpy as np
import usb.backend
import usb.core

from drivers import udev
from drivers.davis import protocol as P
from drivers.davis.device import DavisSource
from drivers.davis.discovery import list_devices
from drivers.davis.models import DATA_ENDPOINT
from drivers.emulator import EmulatorBackend, backend
from edi_live.datatypes import EVENT_DTYPE, Packet
from tests.helpers.recordings import flatten, random_recording


def test_cli_hook_spelling_resolves_to_a_no_argument_factory():
    module, _, name = "drivers.emulator:backend".partition(":")
    factory = getattr(importlib.import_module(module), name)
    be = factory()
    assert isinstance(be, usb.backend.IBackend)
    dev = usb.core.find(idVendor=0x152A, backend=be)
    assert (dev.idProduct, dev.bcdDevice & 0xFF) == (0x841B, 4)  # DAVIS240C on an FX2 board, firmware 4


def test_register_protocol_bytes_on_the_wire():
    be = backend(model="davis346", speed=0)
    dev = usb.core.find(idVendor=0x152A, backend=be)
    # read SYSINFO/1 (chip ID): 4 bytes, big-endian; DAVIS346B is chip 5
    assert bytes(dev.ctrl_transfer(0xC0, 0xBF, 6, 1, 4)) == b"\x00\x00\x00\x05"
    dev.ctrl_transfer(0x40, 0xBF, 2, 12, b"\x00\x01\x02\x03")  # APS exposure, MSB first
    batch = struct.pack(">BBI", 0, 2, 1) + struct.pack(">BBI", 0, 2, 0)  # timestamp reset pulse via 0xC2
    dev.ctrl_transfer(0x40, 0xC2, 2, 0, batch)
    assert be.writes == [(2, 12, 0x00010203), (0, 2, 1), (0, 2, 0)]


def test_loop_replays_forever_with_monotonic_time(rng):
    packets = random_recording(rng, 240, 180, n_events=2000, n_frames=1, n_imu=0, duration_us=100_000)
    want = flatten(packets)[0]
    got, deadline = [], time.monotonic() + 20
    with DavisSource(backend=backend(packets, speed=0, loop=True), policy="wait") as src:
        for p in src:
            if p is not None:
                got.append(p)
            if sum(len(q.events) for q in got) > 2.5 * len(want) or time.monotonic() > deadline:
                src.stop()
    ev, frames, _ = flatten(got)
    assert len(ev) > 2.5 * len(want) and np.all(np.diff(ev["t"]) >= 0) and len(frames) >= 2
    # the second pass repeats the first one's addresses and its relative timing
    second = ev[len(want): 2 * len(want)]
    assert np.array_equal(second[["x", "y", "p"]], want[["x", "y", "p"]])
    assert np.array_equal(np.diff(second["t"]), np.diff(want["t"]))


def test_listing_reports_unreadable_serial_instead_of_failing():
    (d,) = list_devices(backend(speed=0, permission_denied=True))
    assert d.serial is None and "permission denied" in d.error and d.model == "davis240"


def test_each_emulated_camera_has_its_own_serial_so_calibrations_stay_apart(real_recordings, tmp_path):
    # a calibration is kept per model and serial: two recordings (two real cameras) or a colour and a mono sensor
    # emulated under one serial shared the calibration one of them saved
    from drivers.emulator import colour_backend

    first = tmp_path / "first.aedat4"
    second = tmp_path / "second.aedat4"
    data = real_recordings["evlib_sample_davis346.aedat4"].read_bytes()
    first.write_bytes(data)
    second.write_bytes(data)

    def serial(b):
        (d,) = list_devices(b)
        assert d.error is None, d.error
        return d.serial

    by_file = {serial(backend(str(path), speed=0)) for path in (first, second)}
    assert len(by_file) == 2
    assert serial(backend(str(first), speed=0)) == serial(backend(str(first), speed=0))  # stable across runs
    assert serial(backend(str(first), speed=0)) != serial(colour_backend(str(first), speed=0))
    assert serial(backend(speed=0)) != serial(colour_backend(speed=0))
    assert serial(backend(speed=0, serial="ABC123")) == "ABC123"


def test_udev_rule_printed_and_installable(tmp_path, capsys):
    assert udev.main([]) == 0
    assert udev.RULE_TEXT in capsys.readouterr().out
    dest = udev.install(tmp_path, reload=False)
    assert dest.read_text() == udev.RULES_FILE.read_text()
    assert 'ATTR{idVendor}=="152a"' in udev.RULE_TEXT


def test_generated_scene_follows_exposure_and_interval_registers():
    # the driver converts µs to ADC cycles (30 MHz on the emulated DAVIS240); the emulator converts back
    frames, deadline = [], time.monotonic() + 20
    with DavisSource("davis240", backend=backend(speed=0), exposure_us=8000, frame_interval_us=20000) as src:
        for p in src:
            if p is not None:
                frames += p.frames
            if len(frames) >= 4 or time.monotonic() > deadline:
                src.stop()
    assert [f.exposure_us for f in frames[:4]] == [8000] * 4
    assert np.diff([f.exposure_start_us for f in frames[:4]]).tolist() == [20000] * 3


def test_an_unplug_comes_after_the_bytes_asked_not_at_the_first_empty_part(real_recordings):
    # a recording with APS frames yields empty word parts; the first of them unplugged the camera at once
    # (after 364 kB of a 1.5 MB stream, with unplug_after_bytes far beyond the stream)
    from edi_live.aedat4 import Aedat4Reader

    path = real_recordings["evlib_sample_davis346.aedat4"]
    want_events = want_frames = 0
    with Aedat4Reader(path) as reader:  # the recording itself is the oracle
        for stream, data in reader:
            want_events += len(data) if stream.name == "events" else 0
            want_frames += stream.name == "frames"
    got_events = got_frames = 0
    with DavisSource("davis346", backend=backend(path, speed=0, unplug_after_bytes=10**9), policy="wait") as src:
        for p in src:
            if p is not None:
                got_events, got_frames = got_events + len(p.events), got_frames + len(p.frames)
    assert (got_events, got_frames) == (want_events, want_frames) and want_frames > 0


def _one_event_a_millisecond(seconds: int) -> list[Packet]:
    """Events 1 ms apart, in 10 ms packets: each ~1 ms part the emulated camera releases holds one of them."""
    ev = np.zeros(seconds * 1000, EVENT_DTYPE)
    ev["t"] = 1_700_000_000_000_000 + np.arange(len(ev)) * 1000
    ev["x"], ev["y"] = np.arange(len(ev)) % 240, 7
    return [Packet(events=ev[k:k + 10]) for k in range(0, len(ev), 10)]


def _streaming(be: EmulatorBackend) -> EmulatorBackend:
    for module, param, value in P.START_MUX_ON + [(P.DVS, P.DVS_RUN, 1)]:
        be.ctrl_transfer("handle", P.REQ_OUT, P.VR_CONFIG, module, param, array("B", P.pack_value(value)), 0)
    return be


def _released_now(be: EmulatorBackend, limit: int = 5000) -> int:
    """Parts (here 1 ms of device time each) the camera hands over without waiting; up to `limit`."""
    buff = array("B", bytes(1 << 16))
    for n in range(limit):
        try:
            be.bulk_read("handle", DATA_ENDPOINT, 0, buff, 1)
        except usb.core.USBTimeoutError:  # the next part is not due yet
            return n
    return limit


def test_a_suspended_emulator_resumes_at_its_speed_instead_of_bursting_the_backlog(caplog):
    """After Ctrl-Z and fg the emulated camera poured out everything it would have sent while stopped, as fast as
    it was read (as the replay did before drivers.pacing re-anchored it); it now goes on at its speed from where it
    stopped, with one warning. Short lateness is still caught up. The pacing clock is injected: no waiting."""
    now = [1000.0]
    be = _streaming(EmulatorBackend(_one_event_a_millisecond(60), model="davis240", speed=1.0,
                                    clock=lambda: now[0]))
    with caplog.at_level("DEBUG", logger="drivers.pacing"):
        assert _released_now(be) >= 1  # device time 0 is due at once
        now[0] += 0.5
        half_second = _released_now(be)  # half a second later: half a second of parts, caught up
        now[0] += 30.0  # stopped for 30 s
        after_stop = _released_now(be)
        now[0] += 0.5
        resumed = _released_now(be)
        now[0] += 10.0  # stopped again: said at debug level only
        _released_now(be)
    assert 400 <= half_second <= 600, half_second
    assert after_stop <= 2, f"{after_stop} parts burst out after the stop"
    assert abs(resumed - half_second) <= 2, (resumed, half_second)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "paced emulation resumed 30.0 s behind its schedule" in warnings[0], warnings
    assert "\n" not in warnings[0]
    assert sum("behind its schedule" in r.getMessage() for r in caplog.records) == 2


def test_a_timestamp_reset_restarts_the_emulators_schedule_without_a_warning(caplog):
    """Device time restarts at 0 on a timestamp reset: paced against the old anchor, everything after it was
    overdue and poured out until device time caught up with the time since streaming started."""
    now = [1000.0]
    be = _streaming(EmulatorBackend(_one_event_a_millisecond(60), model="davis240", speed=1.0,
                                    clock=lambda: now[0]))
    with caplog.at_level("WARNING", logger="drivers.pacing"):
        for _ in range(10):  # 5 s of streaming, read as it comes
            _released_now(be)
            now[0] += 0.5
        _released_now(be)
        be.ctrl_transfer("handle", P.REQ_OUT, P.VR_CONFIG, P.MUX, P.MUX_TIMESTAMP_RESET, array("B", P.pack_value(1)), 0)
        now[0] += 0.1
        after_reset = _released_now(be)  # what was encoded before the reset, then device time 0 is now
        now[0] += 0.5
        half_second = _released_now(be)
    assert after_reset <= 100 and 400 <= half_second <= 600, (after_reset, half_second)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
