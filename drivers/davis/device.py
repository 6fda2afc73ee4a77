"""`DavisSource`: the live DAVIS240/DAVIS346 source. Opens the camera (version gate, sizes, orientation),
writes libcaer's default configuration, runs the start/stop sequence, and reads endpoint 0x82 on its own
thread into a bounded raw queue that the iterating thread decodes into `Packet`s.

Overflow policy of the raw queue: "drop_oldest" (live: the reader never blocks; dropped chunks are counted
and the decoder re-anchors time and flags `Packet.gap`) or "wait" (emulated replay: lossless).
Any pyusb backend works (`backend=`); an emulator backend may declare `edi_live_epoch_us` (recording time of
device time 0), `edi_live_emulator` and `stream_ended()`; real backends need none of them.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any, Iterator

import numpy as np

from drivers.davis import discovery, models, protocol as P
from drivers.davis.decoder import DavisDecoder
from drivers.davis.transport import UsbTransport, read_serial
from edi_live.datatypes import ColorFilter, Packet, SourceInfo, SourceStatus
from edi_live.errors import (DeviceDisconnectedError, DeviceNotFoundError, ProtocolError, SourceError,
                             UnsupportedFirmwareError)

log = logging.getLogger(__name__)
POLICIES = ("drop_oldest", "wait")
READ_TIMEOUT_MS = 100


class _RawQueue:
    """Bounded queue of (seq, arrival_ns, bytes) between the reader thread and the decoding thread."""

    def __init__(self, max_bytes: int, policy: str) -> None:
        self.max_bytes, self.policy = max_bytes, policy
        self._q: collections.deque = collections.deque()
        self._bytes = 0
        self._cv = threading.Condition()
        self.dropped_bytes = 0
        self.dropped_chunks = 0
        self.end: BaseException | None = None  # error or StopIteration, raised once the queue is empty

    @property
    def backlog_bytes(self) -> int:
        return self._bytes

    def put(self, item: tuple[int, int, bytes], stop: threading.Event) -> None:
        n = len(item[2])
        with self._cv:
            if self.policy == "wait":
                while self._bytes + n > self.max_bytes and self._q and not stop.is_set():
                    self._cv.wait(0.1)
            else:
                while self._bytes + n > self.max_bytes and self._q:
                    old = self._q.popleft()
                    self._bytes -= len(old[2])
                    self.dropped_bytes += len(old[2])
                    self.dropped_chunks += 1
            self._q.append(item)
            self._bytes += n
            self._cv.notify_all()

    def finish(self, end: BaseException) -> None:
        with self._cv:
            if self.end is None:
                self.end = end
            self._cv.notify_all()

    def get(self, timeout_s: float) -> tuple[int, int, bytes] | BaseException | None:
        with self._cv:
            if not self._q and self.end is None:
                self._cv.wait(timeout_s)
            if self._q:
                item = self._q.popleft()
                self._bytes -= len(item[2])
                self._cv.notify_all()
                return item
            return self.end


class DavisSource:
    """A DAVIS camera over pyusb, implementing `edi_live.source.Source`."""

    def __init__(self, model: str = "auto", *, serial: str | None = None, backend: Any = None,
                 exposure_us: int | None = None, frame_interval_us: int | None = None, reconnect: bool = False,
                 policy: str = "drop_oldest", raw_queue_bytes: int = 64 << 20, read_size_bytes: int = 128 << 10,
                 reconnect_timeout_s: float | None = None) -> None:
        if model != "auto":
            models.get_model(model)
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES} (got {policy!r})")
        P.check_exposure(exposure_us, frame_interval_us)
        self.model_name, self.serial, self.backend = model, serial, backend
        self.exposure_us, self.frame_interval_us = exposure_us, frame_interval_us
        self.reconnect, self.policy = reconnect, policy
        self.raw_queue_bytes, self.read_size_bytes = raw_queue_bytes, read_size_bytes
        self.reconnect_timeout_s = reconnect_timeout_s
        size = models.MODELS.get(model)
        self.info = SourceInfo(size.width if size else 0, size.height if size else 0, name=model.upper(),
                               kind=self._kind())
        self.device_info: dict = {}
        self._status = SourceStatus()
        self._stop = threading.Event()       # ends the reader thread (also set internally on close)
        self._user_stop = threading.Event()  # stop() was called: never reopen
        self._transport: UsbTransport | None = None
        self._reader: threading.Thread | None = None
        self._queue: _RawQueue | None = None
        self._decoder: DavisDecoder | None = None
        self._min_time_us = -(2**62)
        self._pending_gap = False
        self._dropped_before = 0  # raw bytes dropped by queues of earlier connections

    def _kind(self) -> str:
        return "emulator" if getattr(self.backend, "edi_live_emulator", False) else "usb"

    # ---- Source protocol ----------------------------------------------------------------------------
    def __enter__(self) -> "DavisSource":
        try:
            self._open()
        except DeviceDisconnectedError as err:  # gone while being started: with --reconnect, wait for it as later
            self._close()
            if not self.reconnect:
                raise
            try:
                self._reopen(err)  # False: stop() ended the wait, and the iteration ends at once
            except BaseException:
                self._close()
                raise
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self._close()

    def stop(self) -> None:
        self._user_stop.set()
        self._stop.set()

    def status(self) -> SourceStatus:
        s = self._status
        if self._queue is not None:
            s.backlog = self._queue.backlog_bytes
        return s

    def __iter__(self) -> Iterator[Packet | None]:
        expected_seq = 0
        while True:
            if self._queue is None or self._user_stop.is_set():
                return  # stop() ends the iteration soon, without decoding the backlog
            item = self._queue.get(0.1)
            if item is None:
                if self._user_stop.is_set():
                    return
                yield None
                continue
            if isinstance(item, BaseException):
                if isinstance(item, StopIteration) or self._user_stop.is_set():
                    return
                if isinstance(item, DeviceDisconnectedError) and self.reconnect:
                    if not self._reopen(item):
                        return
                    expected_seq = 0
                    continue
                raise item
            seq, arrival_ns, data = item
            if seq != expected_seq:
                self._decoder.mark_gap()
                self._status.gaps += 1
                log.warning("USB data arrived faster than it was consumed: dropped %d raw chunks (%d bytes) so far; "
                            "timestamps re-anchored, packet marked as a gap", self._queue.dropped_chunks,
                            self._queue.dropped_bytes)
            expected_seq = seq + 1
            pkt = self._decoder.decode(data, arrival_ns)
            if self._pending_gap:
                pkt.gap, self._pending_gap = True, False
            st = self._status
            st.packets += 1
            st.events += len(pkt.events)
            st.frames += len(pkt.frames)
            st.dropped_bytes = self._queue.dropped_bytes + self._dropped_before
            yield pkt

    # ---- open / configure / start -------------------------------------------------------------------
    def _open(self) -> None:
        self._stop.clear()
        dev = discovery.select_device(self.model_name, self.serial, self.backend)
        serial = None
        try:
            serial = read_serial(dev)
        except SourceError:
            pass  # opening below reports the real problem
        self._transport = t = UsbTransport(dev)
        self._check_versions(t)
        info = self._read_info(t)
        model = models.model_for_chip(info["chip_id"])
        if model is None:
            raise UnsupportedFirmwareError(f"{t.where}: chip ID {info['chip_id']} "
                                           f"({models.CHIP_NAMES.get(info['chip_id'], 'unknown')}) is not supported "
                                           "by edi-live (DAVIS240A/B/C and DAVIS346A/B/C are)")
        self.device_info = info
        dvs_swap = bool(info["dvs_orientation"] & 4)
        w, h = (info["dvs_rows"], info["dvs_columns"]) if dvs_swap else (info["dvs_columns"], info["dvs_rows"])
        self.info = SourceInfo(w, h, name=models.camera_name(info["chip_id"]), serial=serial or "", kind=self._kind(),
                               color_filter=info["color_filter"])
        if self.info.is_color:
            log.info("%s is a colour %s: %s Bayer mosaic", t.where, self.info.name, self.info.color_filter)
        self._configure(t, model, info)
        _warm_up_decoder(info)
        self._start(t, model, info)

    def _reg(self, t: UsbTransport, module: int, param: int) -> int:
        data = t.ctrl_in(P.VR_CONFIG, module, param, 4)
        if len(data) != 4:
            raise ProtocolError(f"{t.where}: register {module}/{param} read returned {len(data)} bytes, expected 4; "
                                "replug the camera")
        return P.unpack_value(data)

    def _write(self, t: UsbTransport, writes: list[P.Write]) -> None:
        for m, p, v in writes:
            t.ctrl_out(P.VR_CONFIG, m, p, P.pack_value(v))

    def _check_versions(self, t: UsbTransport) -> None:
        need_fw = models.FIRMWARE_VERSION[t.dev.idProduct]
        if t.firmware_version != need_fw:
            raise UnsupportedFirmwareError(f"{t.where} has firmware {t.firmware_version}, edi-live needs firmware "
                                           f"{need_fw}: {models.FLASHY_HINT}")
        logic = self._reg(t, P.SYSINFO, P.SYS_LOGIC_VERSION)
        patch = self._reg(t, P.SYSINFO, P.SYS_LOGIC_PATCH) if logic == models.LOGIC_VERSION else 0
        if logic != models.LOGIC_VERSION or patch < models.LOGIC_MIN_PATCH:
            raise UnsupportedFirmwareError(f"{t.where} runs FPGA/CPLD logic {logic}.{patch}, edi-live needs logic "
                                           f"{models.LOGIC_VERSION}.{models.LOGIC_MIN_PATCH} or newer patch: "
                                           f"{models.FLASHY_HINT}")

    def _read_info(self, t: UsbTransport) -> dict:
        r = lambda m, p: self._reg(t, m, p)  # noqa: E731
        info = {
            "chip_id": r(P.SYSINFO, P.SYS_CHIP_ID), "is_master": r(P.SYSINFO, P.SYS_IS_MASTER),
            "clocks": P.Clocks.from_registers(r(P.SYSINFO, P.SYS_LOGIC_CLOCK), r(P.SYSINFO, P.SYS_ADC_CLOCK),
                                              r(P.SYSINFO, P.SYS_USB_CLOCK), r(P.SYSINFO, P.SYS_CLOCK_DEVIATION)),
            "dvs_columns": r(P.DVS, P.DVS_SIZE_COLUMNS), "dvs_rows": r(P.DVS, P.DVS_SIZE_ROWS),
            "dvs_orientation": r(P.DVS, P.DVS_ORIENTATION),
            "aps_columns": r(P.APS, P.APS_SIZE_COLUMNS), "aps_rows": r(P.APS, P.APS_SIZE_ROWS),
            "aps_orientation": r(P.APS, P.APS_ORIENTATION),
            "has_global_shutter": bool(r(P.APS, P.APS_HAS_GLOBAL_SHUTTER)),
            "imu_type": r(P.IMU, P.IMU_TYPE), "imu_orientation": r(P.IMU, P.IMU_ORIENTATION),
            "dvs_features": {p: r(P.DVS, p) for p in (P.DVS_HAS_PIXEL_FILTER, P.DVS_HAS_BA_FILTER,
                                                     P.DVS_HAS_ROI_FILTER, P.DVS_HAS_SKIP_FILTER,
                                                     P.DVS_HAS_POLARITY_FILTER)},
        }
        info["color_filter"] = self._color_filter(t, r(P.APS, P.APS_COLOR_FILTER))
        for key in ("dvs_columns", "dvs_rows", "aps_columns", "aps_rows"):
            if not 0 < info[key] <= 4096:
                raise ProtocolError(f"{t.where}: {key} register reads {info[key]}, expected 1..4096; replug the camera")
        if info["clocks"].adc_mhz <= 0:
            raise ProtocolError(f"{t.where}: ADC clock register reads 0 MHz; replug the camera")
        return info

    @staticmethod
    def _color_filter(t: UsbTransport, code: int) -> ColorFilter | None:
        """The sensor's Bayer pattern from the APS colour-filter register (libcaer's code, see models)."""
        try:
            return models.color_filter_of_code(code)
        except ValueError as exc:
            log.warning("%s: %s; its APS frames are read as grey", t.where, exc)
            return None

    def _configure(self, t: UsbTransport, model: models.DavisModel, info: dict) -> None:
        # like libcaer, the ROI and filter limits use the sizes as reported to the user (after any X/Y swap)
        aps_w, aps_h = info["aps_columns"], info["aps_rows"]
        if info["aps_orientation"] & 4:
            aps_w, aps_h = aps_h, aps_w
        dvs_w, dvs_h = info["dvs_columns"], info["dvs_rows"]
        if info["dvs_orientation"] & 4:
            dvs_w, dvs_h = dvs_h, dvs_w
        exposure_us = self.exposure_us if self.exposure_us is not None else P.DEFAULT_EXPOSURE_US
        interval_us = self.frame_interval_us if self.frame_interval_us is not None else P.DEFAULT_FRAME_INTERVAL_US
        self._write(t, P.default_config(model, has_global_shutter=info["has_global_shutter"], aps_columns=aps_w,
                                        aps_rows=aps_h, clocks=info["clocks"], exposure_us=exposure_us,
                                        frame_interval_us=interval_us, dvs_features=info["dvs_features"],
                                        dvs_columns=dvs_w, dvs_rows=dvs_h))

    def _start(self, t: UsbTransport, model: models.DavisModel, info: dict) -> None:
        sleep = (lambda s: None) if getattr(self.backend, "edi_live_emulator", False) else time.sleep
        self._write(t, P.START_ALL_OFF)
        sleep(P.START_SLEEPS_S["drain"])
        t.clear_halt()
        self._queue = _RawQueue(self.raw_queue_bytes, self.policy)
        self._write(t, P.START_CHIP_ON)
        sleep(P.START_SLEEPS_S["chip"])
        self._write(t, P.START_MUX_ON)
        epoch_us = getattr(self.backend, "edi_live_epoch_us", None)
        if epoch_us is None:
            epoch_us = time.time_ns() // 1000  # device time 0 ~ now: timestamps become Unix µs like DV's
        epoch_us = max(int(epoch_us), self._min_time_us)
        self._decoder = DavisDecoder(info["dvs_columns"], info["dvs_rows"], info["aps_columns"], info["aps_rows"],
                                     dvs_orientation=info["dvs_orientation"], aps_orientation=info["aps_orientation"],
                                     imu_orientation=info["imu_orientation"], imu_type=info["imu_type"],
                                     adc_x2=model.adc_x2, time_offset_us=epoch_us,
                                     color_filter=info["color_filter"])
        self._decoder.anchor(time.monotonic_ns())  # device time 0 ~ now (MUX and timestamps just started)
        self._reader = threading.Thread(target=self._read_loop, args=(t, self._queue), name="usb-reader",
                                        daemon=True)
        self._reader.start()
        sleep(P.START_SLEEPS_S["mux"])
        self._write(t, P.START_PRODUCERS_ON)

    # ---- reader thread --------------------------------------------------------------------------------
    def _read_loop(self, t: UsbTransport, q: _RawQueue) -> None:
        seq = 0
        ended = getattr(self.backend, "stream_ended", None)
        try:
            while not self._stop.is_set():
                data = t.read(self.read_size_bytes, READ_TIMEOUT_MS)
                if data:
                    q.put((seq, time.monotonic_ns(), data), self._stop)
                    seq += 1
                elif callable(ended) and ended():
                    q.finish(StopIteration())
                    return
            q.finish(StopIteration())
        except BaseException as exc:  # handed to the iterating thread after the data already queued
            q.finish(exc if isinstance(exc, SourceError) else SourceError(f"USB reader failed: {exc!r}"))

    # ---- stop / reconnect -----------------------------------------------------------------------------
    def _close(self) -> None:
        self._stop.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
            self._reader = None
        t, self._transport = self._transport, None
        if t is not None:
            try:
                self._write(t, P.STOP_SEQUENCE)
            except SourceError:
                pass  # unplugged: nothing to stop
            t.close()

    def _reopen(self, err: DeviceDisconnectedError) -> bool:
        """Wait for the camera to come back (same model/serial), then restart streaming with a gap mark."""
        last_wm = self._decoder.watermark_us if self._decoder else self._min_time_us
        self._dropped_before += self._queue.dropped_bytes if self._queue else 0
        where = self._transport.where if self._transport is not None else f"the {self.model_name}"
        self._close()
        log.warning("%s was disconnected; waiting for it to come back (--reconnect)", where)
        away = time.monotonic()
        deadline = None if self.reconnect_timeout_s is None else time.monotonic() + self.reconnect_timeout_s
        while not self._user_stop.is_set():
            self._stop.clear()
            try:
                self._min_time_us = last_wm
                self._open()
                self._pending_gap = True
                self._status.gaps += 1
                log.warning("%s is back after %.1f s; resumed (what it saw meanwhile is lost, marked as a gap)",
                            where, time.monotonic() - away)
                return True
            except (DeviceNotFoundError, DeviceDisconnectedError):
                self._close()  # not back yet
            if deadline is not None and time.monotonic() > deadline:
                raise err
            if self._user_stop.wait(0.2):
                return False
        return False


def _warm_up_decoder(info: dict) -> None:
    """Decode a few synthetic words before the camera streams.

    The decoder's hot loop is a numba kernel: compiled on first use (about 2 s with a cold cache) or loaded from
    the on-disk cache. Doing that now, rather than on the first USB chunk, keeps the raw queue from backing up
    (and, live, from dropping data) at start-up.
    """
    from drivers.davis.encoder import WordEncoder

    w, h = int(info["dvs_columns"]), int(info["dvs_rows"])
    n = 64
    t = np.arange(n, dtype=np.int64) * 10
    x, y = np.arange(n, dtype=np.int64) % w, np.arange(n, dtype=np.int64) % h
    words = WordEncoder(w, h).encode_events(t, x, y, (np.arange(n) % 2).astype(bool))
    DavisDecoder(w, h, info["aps_columns"], info["aps_rows"]).decode_words(np.asarray(words, dtype=np.uint16))
