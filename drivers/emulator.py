"""An emulated DAVIS240C/DAVIS346 camera as a pyusb backend, so the unchanged driver runs without hardware.

`backend()` returns a `usb.backend.IBackend` presenting the camera's descriptors, answering the 0xBF/0xC2
register protocol from a register file (versions, chip ID, sizes, orientation; every write is recorded), and
streaming the 16-bit word stream synthesised by `drivers.davis.encoder` from a recording (an .aedat4 path read
through `drivers.replay.merged_packets`, or any iterable of `Packet`s) or, with no recording, from a generated
scene. Pacing maps device time to host time (`speed`, 0 = as fast as read) with drivers.pacing's Pacer on an
injectable `clock`, anchored by the first part read after streaming starts and again after a timestamp reset; a
stall of more than pacing.MAX_LATE_S (Ctrl-Z and fg) goes on from where it stopped, with one warning, as the replay
does, instead of bursting the backlog. Faults are injected by keyword: no_device, permission_denied, busy,
logic_version/logic_patch/firmware, unplug_after_bytes (+ replug_after_s), garbage_words (random words inserted),
drop_words (words removed: truncated columns, lost rows), reset_at_us (timestamp reset mid-stream). Options: serial
(default: one per recording file and per colour or mono sensor, `default_serial`), width/height, color_filter (a
colour DAVIS346: the APS colour-filter register answers libcaer's code of this Bayer pattern and APS frames are
sent as its mosaic; default: the recording's pattern, or mono), dvs_orientation, aps_orientation, imu_orientation,
chip_id, seed, holdback_us (how far events are held back so that a frame, which arrives after the events of its
exposure, can still be sent at its exposure start; default 200 ms).
Data is released in ~1 ms parts of device time, like a camera's 1 ms early-packet delay. On unplug the part in
flight is lost; after `replug_after_s` the device reappears and its clock restarts at 0.

Usable as `edi-live --usb-backend drivers.emulator:backend` (generated scene; `drivers.emulator:colour_backend`
for a colour DAVIS346); `--emulate-from FILE` makes the CLI call `backend(recording=FILE, model=...)`.
"""

from __future__ import annotations

import errno
import os
import threading
import time
import zlib
from array import array
from typing import Any, Callable

import numpy as np
import usb.backend
import usb.core

from drivers.davis import models, protocol as P
from drivers.davis.encoder import WordEncoder
from drivers.davis.wordstream import WordStream
from drivers.emulator_recording import as_sensor_frames, is_path, recording_color_filter, recording_factory, recording_size
from drivers.pacing import Pacer
from edi_live.datatypes import COLOR_FILTERS, ColorFilter
from edi_live.errors import RecordingError
from edi_live.simulation.stream import generated_scene

_FAULTS = {"no_device", "permission_denied", "busy", "logic_version", "logic_patch", "firmware",
           "unplug_after_bytes", "replug_after_s", "garbage_words", "drop_words", "reset_at_us", "serial", "width",
           "height", "color_filter", "dvs_orientation", "aps_orientation", "imu_orientation", "chip_id", "seed", "holdback_us"}


class _Desc:
    def __init__(self, **kw: Any) -> None:
        self.extra_descriptors = []
        self.__dict__.update(kw)


def _usb_error(msg: str, code: int, backend_code: int) -> usb.core.USBError:
    return usb.core.USBError(msg, backend_code, code)


# ---- the pyusb backend ---------------------------------------------------------------------------------
class EmulatorBackend(usb.backend.IBackend):
    """A pyusb backend with one emulated DAVIS on bus 1, address 7."""

    edi_live_emulator = True

    def __init__(self, recording: Any = None, *, model: str | None = None, speed: float = 1.0, loop: bool = False,
                 clock: Callable[[], float] = time.monotonic, **faults: Any) -> None:
        unknown = set(faults) - _FAULTS
        if unknown:
            raise TypeError(f"unknown emulator options {sorted(unknown)} (known: {sorted(_FAULTS)})")
        if speed < 0:
            raise ValueError(f"speed must be >= 0 (got {speed})")
        self.faults = faults
        self.speed = float(speed)
        self.aps_timing = {"exposure_us": 4000, "interval_us": 40000}  # the generated scene follows APS/12, 13
        if recording is not None and not is_path(recording):
            recording = list(recording)  # in-memory packets: read twice (size, then stream)
        size = recording_size(recording) if recording is not None else None
        pattern = faults.get("color_filter") or (recording_color_filter(recording) if recording is not None else None)
        if pattern and pattern not in COLOR_FILTERS:
            raise ValueError(f"unknown Bayer pattern {pattern!r} (known: {', '.join(COLOR_FILTERS)})")
        self.color_filter: ColorFilter | None = pattern or None
        mdl = models.get_model(model) if model else (models.DAVIS240 if size is None or size == (240, 180)
                                                      else models.DAVIS346)
        self.model = mdl
        w = int(faults.get("width") or (size[0] if size else mdl.width))
        h = int(faults.get("height") or (size[1] if size else mdl.height))
        self.width, self.height = w, h
        dvs_o, aps_o = int(faults.get("dvs_orientation", 0)), int(faults.get("aps_orientation", 0))
        imu_o = int(faults.get("imu_orientation", 0))
        self.encoder = WordEncoder(w, h, dvs_orientation=dvs_o, aps_orientation=aps_o, imu_orientation=imu_o,
                                   adc_x2=mdl.adc_x2)
        if recording is None:
            epoch = time.time_ns() // 1000
            seed = int(faults.get("seed", 7))
            factory = lambda: generated_scene(w, h, epoch_us=epoch, seed=seed, timing=self.aps_timing,  # noqa: E731
                                              color_filter=self.color_filter)
        else:
            packets = recording_factory(recording, self._recording_fault)
            factory = lambda: as_sensor_frames(packets(), self.color_filter)  # noqa: E731
        self.stream = WordStream(factory, self.encoder, loop, int(faults.get("holdback_us", 200_000)),
                                  faults.get("reset_at_us"))
        self.regs = self._register_file(mdl, w, h, dvs_o, aps_o, imu_o)
        self.writes: list[tuple[int, int, int]] = []
        self.serial = str(faults.get("serial", default_serial(recording, self.color_filter)))[:8]
        self._lock = threading.Lock()
        self._pending: list[tuple[bytes, int]] = []  # (data, device time it reaches)
        self._sent_bytes = 0
        self._unplugged_at: float | None = None
        self._opened = 0
        self._claimed = False
        self._clock = clock
        self._pacer = Pacer(self.speed, clock, name="emulation")
        self._paced_t: int | None = None  # device time of the last part released
        self._garbage = int(faults.get("garbage_words", 0))
        self._drop_words = int(faults.get("drop_words", 0))
        self._rng = np.random.default_rng(int(faults.get("seed", 7)))
        self._stream_epoch: int | None = None
        self._fault: RecordingError | None = None

    def _recording_fault(self, exc: RecordingError) -> None:
        """The recording is damaged: no further pass (no loop); raised once everything before it was read."""
        self._fault = exc
        self.stream.loop = False

    def _raise_fault_at_end_locked(self) -> None:
        if self._fault is not None and self.stream.done and not self._pending:
            raise self._fault

    # -- register file --
    def _register_file(self, mdl: models.DavisModel, w: int, h: int, dvs_o: int, aps_o: int, imu_o: int) -> dict:
        dcols, drows = (h, w) if dvs_o & 4 else (w, h)
        acols, arows = (h, w) if aps_o & 4 else (w, h)
        regs = {
            (P.SYSINFO, P.SYS_LOGIC_VERSION): int(self.faults.get("logic_version", models.LOGIC_VERSION)),
            (P.SYSINFO, P.SYS_LOGIC_PATCH): int(self.faults.get("logic_patch", models.LOGIC_MIN_PATCH)),
            (P.SYSINFO, P.SYS_CHIP_ID): int(self.faults.get("chip_id", mdl.chip_id)),
            (P.SYSINFO, P.SYS_IS_MASTER): 1, (P.SYSINFO, P.SYS_LOGIC_CLOCK): 104 if mdl.adc_x2 else 100,
            (P.SYSINFO, P.SYS_ADC_CLOCK): 30 if mdl.adc_x2 else 100,
            (P.SYSINFO, P.SYS_USB_CLOCK): 30 if mdl.adc_x2 else 80,
            (P.SYSINFO, P.SYS_CLOCK_DEVIATION): 1000,
            (P.DVS, P.DVS_SIZE_COLUMNS): dcols, (P.DVS, P.DVS_SIZE_ROWS): drows, (P.DVS, P.DVS_ORIENTATION): dvs_o & 4,
            (P.APS, P.APS_SIZE_COLUMNS): acols, (P.APS, P.APS_SIZE_ROWS): arows, (P.APS, P.APS_ORIENTATION): aps_o & 7,
            (P.APS, P.APS_HAS_GLOBAL_SHUTTER): 1,
            (P.APS, P.APS_COLOR_FILTER): models.code_of_color_filter(self.color_filter), (P.IMU, P.IMU_TYPE): 1, (P.IMU, P.IMU_ORIENTATION): imu_o & 7,
            (P.MUX, P.MUX_HAS_STATISTICS): 0, (P.DVS, P.DVS_HAS_BA_FILTER): 1, (P.DVS, P.DVS_HAS_ROI_FILTER): 1,
        }
        return regs

    @property
    def streaming(self) -> bool:
        r = self.regs
        return bool(r.get((P.MUX, P.MUX_RUN)) and r.get((P.USB, P.USB_RUN)) and r.get((P.MUX, P.MUX_TIMESTAMP_RUN)))

    @property
    def producing(self) -> bool:
        """Streaming with a producer switched on: only then does a camera send data (the driver may still be
        finishing its start sequence before that)."""
        r = self.regs
        return self.streaming and any(r.get(k) for k in ((P.DVS, P.DVS_RUN), (P.APS, P.APS_RUN),
                                                         (P.IMU, P.IMU_RUN_ACCEL), (P.IMU, P.IMU_RUN_GYRO)))

    @property
    def edi_live_epoch_us(self) -> int | None:
        """Recording time of device time 0 (the driver adds it so timestamps match the recording)."""
        with self._lock:
            self.stream.ensure_shift()
            return self.stream.shift

    def stream_ended(self) -> bool:
        with self._lock:
            if not self.stream.done and self.producing and not self._pending:
                self._fill_locked()
            return self.stream.done and not self._pending and self._fault is None  # a fault: bulk_read raises it

    def _present(self) -> bool:
        if self.faults.get("no_device"):
            return False
        if self._unplugged_at is not None:
            replug = self.faults.get("replug_after_s")
            if replug is None or time.monotonic() - self._unplugged_at < replug:
                return False
            self._unplugged_at = None  # plugged back in
        return True

    # -- IBackend: descriptors --
    def enumerate_devices(self):
        if self._present():
            yield "emulated-davis"

    def get_device_descriptor(self, dev):
        return _Desc(bLength=18, bDescriptorType=1, bcdUSB=0x0200 if self.model.adc_x2 else 0x0300,
                     bDeviceClass=0xFF, bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64,
                     idVendor=models.VENDOR_ID, idProduct=self.model.product_id,
                     bcdDevice=int(self.faults.get("firmware", self.model.firmware)), iManufacturer=1, iProduct=2,
                     iSerialNumber=3, bNumConfigurations=1, address=7, bus=1, port_number=1, port_numbers=(1,),
                     speed=3 if self.model.adc_x2 else 4)

    def get_configuration_descriptor(self, dev, config):
        return _Desc(bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1, bConfigurationValue=1,
                     iConfiguration=0, bmAttributes=0x80, bMaxPower=250)

    def get_interface_descriptor(self, dev, intf, alt, config):
        return _Desc(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=1,
                     bInterfaceClass=0xFF, bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        return _Desc(bLength=7, bDescriptorType=5, bEndpointAddress=models.DATA_ENDPOINT, bmAttributes=2,
                     wMaxPacketSize=self.model.max_packet_bytes, bInterval=0, bRefresh=0, bSynchAddress=0)

    # -- IBackend: handles --
    def open_device(self, dev):
        if not self._present():
            raise _usb_error("No such device (it may have been disconnected)", errno.ENODEV, -4)
        if self.faults.get("permission_denied"):
            raise _usb_error("Access denied (insufficient permissions)", errno.EACCES, -3)
        self._opened += 1
        return "handle"

    def close_device(self, dev_handle):
        self._opened = max(0, self._opened - 1)

    def get_configuration(self, dev_handle):
        return 1

    def set_configuration(self, dev_handle, config_value):
        pass

    def claim_interface(self, dev_handle, intf):
        if self.faults.get("busy"):
            raise _usb_error("Resource busy", errno.EBUSY, -6)
        self._claimed = True

    def release_interface(self, dev_handle, intf):
        self._claimed = False

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def clear_halt(self, dev_handle, ep):
        self._check_plugged()
        with self._lock:
            self._pending.clear()

    def _check_plugged(self) -> None:
        if self._unplugged_at is not None:
            raise _usb_error("No such device (it may have been disconnected)", errno.ENODEV, -4)

    # -- control transfers --
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self._check_plugged()
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR(string)
            idx = wValue & 0xFF
            text = {1: "iniVation", 2: self.model.chip_name, 3: self.serial}.get(idx, "")
            payload = b"\x09\x04" if idx == 0 else text.encode("utf-16-le")
            desc = bytes([2 + len(payload), 3]) + payload
            n = min(len(data), len(desc))
            data[:n] = array("B", desc[:n])
            return n
        if bmRequestType == P.REQ_IN and bRequest == P.VR_CONFIG:
            value = P.pack_value(self.regs.get((wValue, wIndex), 0))
            data[:4] = array("B", value)
            return 4
        if bmRequestType == P.REQ_OUT and bRequest == P.VR_CONFIG:
            self._write(wValue, wIndex, P.unpack_value(bytes(data)))
            return len(data)
        if bmRequestType == P.REQ_OUT and bRequest == P.VR_CONFIG_MULTIPLE:
            for m, p, v in P.unpack_multiple(wValue, bytes(data)):
                self._write(m, p, v)
            return len(data)
        raise _usb_error("Pipe error", errno.EPIPE, -9)  # a STALL, as a device does for unknown requests

    def _write(self, module: int, param: int, value: int) -> None:
        self.writes.append((module, param, value))
        if (module, param) in ((P.SYSINFO, p) for p in range(8)):
            return  # read-only
        was = self.streaming
        self.regs[(module, param)] = value
        if module == P.APS and param in (P.APS_EXPOSURE, P.APS_FRAME_INTERVAL):
            adc_mhz = self.regs[(P.SYSINFO, P.SYS_ADC_CLOCK)] * self.regs[(P.SYSINFO, P.SYS_CLOCK_DEVIATION)] / 1000
            key = "exposure_us" if param == P.APS_EXPOSURE else "interval_us"
            self.aps_timing[key] = P.cycles_to_us(value, adc_mhz)
        if module == P.MUX and param == P.MUX_TIMESTAMP_RESET and value == 1:
            with self._lock:
                if self.stream.shift is not None and self.encoder.started:
                    self.stream.shift += self.encoder.last_t
                    self._pending.append((self.encoder.timestamp_reset().tobytes(), 0))
        if self.streaming and not was:  # (re)start: like a power-cycled camera, device time restarts at 0
            with self._lock:
                if self.stream.shift is not None and self.encoder.started:
                    self.stream.shift += self.encoder.last_t
                    self.encoder.timestamp_reset()
                self._pacer = Pacer(self.speed, self._clock, name="emulation")  # anchored by the first part read
                self._paced_t = None

    # -- bulk data --
    def _fill_locked(self, need_one: bool = False) -> None:
        while (need_one or not self._pending) and not self.stream.done:
            blk = self.stream.next_block()
            if blk is None:
                return
            for words, dev_t in blk:
                if self._garbage and len(words) > 64:
                    k = min(self._garbage, 3)
                    pos = self._rng.integers(0, len(words) + 1, k)
                    words = np.insert(words, np.sort(pos), self._rng.integers(0, 0x10000, k).astype(np.uint16))
                    self._garbage -= k
                if self._drop_words and len(words) > 64:  # truncation: words lost inside the device/cable
                    k = min(self._drop_words, 3)
                    words = np.delete(words, self._rng.choice(len(words), k, replace=False))
                    self._drop_words -= k
                self._pending.append((words.tobytes(), dev_t))
            need_one = False

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        self._check_plugged()
        deadline = time.monotonic() + (timeout or 1000) / 1000.0
        while True:
            with self._lock:
                if self.producing:
                    self._fill_locked()
                    n = self._take_locked(buff)
                    if n:
                        return n
                    self._raise_fault_at_end_locked()
            wait = deadline - time.monotonic()
            if wait <= 0:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(min(wait, 0.002))

    def _take_locked(self, buff) -> int:
        if not self._pending:
            return 0
        data, dev_t = self._pending[0]
        if not self._pacer.unpaced:
            if self._paced_t is not None and dev_t < self._paced_t:  # a timestamp reset: device time restarts
                self._pacer.anchor(dev_t)
            if self._pacer.delay_s(dev_t) > 0:
                return 0
            self._paced_t = dev_t
        limit = self.faults.get("unplug_after_bytes")
        n = min(len(buff), len(data))
        if limit is not None:
            if int(limit) <= self._sent_bytes:  # (not n == 0: an empty part is no reason to unplug)
                self._unplug()
            n = min(n, int(limit) - self._sent_bytes)
        buff[:n] = array("B", data[:n])
        self._pending[0] = (data[n:], dev_t)
        if not self._pending[0][0]:
            self._pending.pop(0)
        self._sent_bytes += n
        return n

    def _unplug(self) -> None:
        self._unplugged_at = time.monotonic()
        self.faults["unplug_after_bytes"] = None  # after a replug the stream continues
        self.regs[(P.MUX, P.MUX_RUN)] = 0
        self._pending.clear()
        raise _usb_error("No such device (it may have been disconnected)", errno.ENODEV, -4)


def default_serial(recording: Any, color_filter: ColorFilter | None) -> str:
    """The emulated camera's serial when none is given: one per recording file (its name and size) and per colour
    or mono sensor, so that a calibration saved for one emulated camera (kept by model and serial, as for a real
    one) is not picked up by another; "EMU00001" for the generated mono scene, as before."""
    if is_path(recording):
        path = os.fsdecode(recording)
        try:
            size = os.path.getsize(path)
        except OSError:
            size = -1
        key = f"{os.path.basename(path)}:{size}:{color_filter or 'mono'}"
        return f"EMF{zlib.crc32(key.encode()) % 16**5:05X}"
    if recording is None:
        return "EMU00001" if color_filter is None else f"EMUC{color_filter}"
    return "EMU00001" if color_filter is None else "EMUC0001"  # packets handed in: no name to tell them apart


def backend(recording: Any = None, *, model: str | None = None, speed: float = 1.0, loop: bool = False,
            **faults: Any) -> usb.backend.IBackend:
    """An emulated DAVIS as a pyusb backend. No arguments: a DAVIS240C showing a generated scene.

    recording: an .aedat4 path or an iterable of Packets; model: "davis240" or "davis346" (default: from the
    recording's size); speed: 1.0 real time, 0 unpaced; loop: replay the recording forever; faults: see module doc.
    """
    return EmulatorBackend(recording, model=model, speed=speed, loop=loop, **faults)


def colour_backend(recording: Any = None, **options: Any) -> usb.backend.IBackend:
    """An emulated colour DAVIS346 (RGGB, the DAVIS346 colour's pattern, unless `color_filter` says otherwise)."""
    options.setdefault("model", "davis346")
    options.setdefault("color_filter", "RGGB")
    return EmulatorBackend(recording, **options)
