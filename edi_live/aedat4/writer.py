"""AEDAT 4.0 writer: events, frames (exposure window and frame source), IMU and triggers.

Owns: the IOHeader (dataTablePosition stored explicitly so it can be patched in place), the infoNode XML, one
compressed packet per write call (LZ4 by default, zstd or none), per-stream monotonic-time checks (DV tools reject
anything else), and the FileDataTable written at close() with `dataTablePosition` patched, so DV tools can seek.
close() runs from `__exit__` even when the block raised, so the file is always finalised; a packet whose write
failed (a full disk) is cut off whole, which usually leaves room for the table, so what came before it is kept in a
finalised file.
"""

from __future__ import annotations

import contextlib
import os
import stat
import struct
from xml.sax.saxutils import escape

import numpy as np

from edi_live.aedat4 import schema as S
from edi_live.aedat4.compression import compressor
from edi_live.aedat4.header import COLOR_FILTER_KEY
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, ColorFilter, Frame, as_events
from edi_live.errors import RecordingError

def _mode(path: str) -> int:
    try:
        return os.stat(path).st_mode
    except OSError:
        return 0  # not there (yet): open() creates it or says why not


_STREAMS = (("events", "EVTS"), ("frames", "FRME"), ("imu", "IMUS"), ("triggers", "TRIG"))
MAX_EVENTS_PER_PACKET = 1 << 20  # larger write_events() calls are split, keeping packets (and readers) bounded

# IMU element table: soffset, t, temperature, accel xyz, gyro xyz, mag xyz (itemsize 56: 4 mod 8 start + 52 + pad)
_IMU_REC = np.dtype({"names": ["so", "t", "f"], "formats": ["<i4", "<i8", ("<f4", (10,))],
                     "offsets": [0, 4, 12], "itemsize": 56})
_IMU_SLOTS = [4] + [12 + 4 * i for i in range(10)]
_TRIG_REC = np.dtype({"names": ["so", "t", "type"], "formats": ["<i4", "<i8", "i1"],
                      "offsets": [0, 4, 12], "itemsize": 16})
_TRIG_SLOTS = [4, 12]
# FileDataDefinition: soffset, ByteOffset, PacketInfo{stream, size}, NumElements, TimestampStart, TimestampEnd
_FTAB_REC = np.dtype({"names": ["so", "off", "sid", "size", "n", "t0", "t1"],
                      "formats": ["<i4", "<i8", "<i4", "<i4", "<i8", "<i8", "<i8"],
                      "offsets": [0, 4, 12, 16, 20, 28, 36], "itemsize": 48})
_FTAB_SLOTS = [4, 12, 20, 28, 36]


class Aedat4Writer:
    """Write an AEDAT4 file that dv-processing and `aedat` open. A context manager; always call close()."""

    def __init__(self, path: str | os.PathLike, width: int, height: int, *, events: bool = True,
                 frames: bool = True, imu: bool = False, triggers: bool = False, compression: str = "lz4",
                 camera_name: str = "edi-live", frame_source: str = "aps",
                 color_filter: ColorFilter | None = None) -> None:
        self.path = os.fspath(path)
        if compression not in S.COMPRESSION_CODES:
            raise RecordingError(f"unknown compression '{compression}' (use one of {', '.join(S.COMPRESSION_CODES)})",
                                 self.path)
        if frame_source not in S.FRAME_SOURCES:
            raise RecordingError(f"unknown frame source '{frame_source}' (use one of "
                                 f"{', '.join(S.FRAME_SOURCES)})", self.path)
        if not (0 < width < 32768 and 0 < height < 32768):
            raise RecordingError(f"invalid resolution {width}x{height}", self.path)
        self.width, self.height = int(width), int(height)
        self.compression = compression
        self.camera_name = camera_name
        self.color_filter = color_filter  # gray frames are raw mosaics of this pattern (stream metadata)
        self._frame_source = S.FRAME_SOURCES[frame_source]
        wanted = {"events": events, "frames": frames, "imu": imu, "triggers": triggers}
        self._ids = {}
        for name, _ in _STREAMS:
            if wanted[name]:
                self._ids[name] = len(self._ids)
        self._last_t = {name: -(2**63) for name in self._ids}
        self._compress = compressor(compression)
        self._table: list[tuple[int, int, int, int, int, int]] = []
        self._closed = False
        if stat.S_ISFIFO(_mode(self.path)):  # opening one blocks until a reader comes, and no signal ends that
            raise RecordingError("cannot write a recording to a pipe or terminal: an AEDAT4 file is finalised by "
                                 "seeking back into it; give a file name", self.path)
        try:
            # unbuffered: each packet is one write of our own, so a failed one (a full disk) can be cut off whole,
            # with no part of it left in a buffer to be written later
            self._file = open(self.path, "wb", buffering=0)
        except OSError as exc:
            raise RecordingError(f"cannot create the recording ({exc.strerror or exc})", self.path) from exc
        if not self._file.seekable():  # a pipe or terminal: the table's offsets and the header patch need seeking
            self._file.close()
            raise RecordingError("cannot write a recording to a pipe or terminal: an AEDAT4 file is finalised by "
                                 "seeking back into it; give a file name", self.path)
        # -1 ("no table") is stored explicitly, not omitted as a FlatBuffers default, so close() can patch it in
        # place; a recording cut off before close() then reads as an interrupted recording in every DV tool
        header, positions = self._header(-1)
        self._dtp_pos = len(S.MAGIC) + positions[S.IOH_DATA_TABLE_POSITION]
        self._write(S.MAGIC + header)

    # ------------------------------------------------------------------------------------------ header
    def _xml(self) -> bytes:
        streams = [(sid, type_id, name) for name, type_id in _STREAMS if (sid := self._ids.get(name)) is not None]
        return info_xml(streams, self.width, self.height, self.camera_name, self.compression,
                        color_filter=self.color_filter)

    def _header(self, dtp: int) -> tuple[bytes, dict[int, int]]:
        return io_header(self.compression, dtp, self._xml())

    # ------------------------------------------------------------------------------------------ writing
    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        try:
            while view:
                view = view[self._file.write(view):]  # a raw write may take part of it (the disk filling up)
        except OSError as exc:
            raise RecordingError(f"cannot write the recording ({exc.strerror or exc})", self.path,
                                 self._file.tell()) from exc

    def _write_whole(self, data: bytes) -> None:
        """Write `data`, or on failure leave the file as it was before (so that close() can still finalise what
        was written before a full disk: the cut-off part frees room for the table)."""
        start = self._file.tell()
        try:
            self._write(data)
        except RecordingError:
            with contextlib.suppress(OSError):
                self._file.truncate(start)
                self._file.seek(start)
            raise

    def _check(self, name: str, t_first: int, t_last: int) -> None:
        if self._closed:
            raise RecordingError("write after close()", self.path)
        if name not in self._ids:
            raise RecordingError(f"this writer was opened without a {name} stream", self.path)
        if t_first < self._last_t[name]:
            raise RecordingError(f"{name} timestamps go backwards ({t_first} µs after {self._last_t[name]} µs); "
                                 f"AEDAT4 streams must be in time order", self.path)

    def _check_sorted(self, name: str, t: np.ndarray) -> None:
        if len(t) > 1 and bool((t[1:] < t[:-1]).any()):
            raise RecordingError(f"{name} passed to the writer are not sorted by time", self.path)
        self._check(name, int(t[0]), int(t[-1]))

    def _accept(self, name: str, records: np.ndarray, dtype: np.dtype, dtype_name: str) -> bool:
        """write_<name>'s input checks: RecordingError unless `dtype` and sorted by t; False when empty."""
        if records.dtype != dtype:
            raise RecordingError(f"write_{name} needs {dtype_name}, got {records.dtype}", self.path)
        if not len(records):
            return False
        self._check_sorted(name, records["t"])
        return True

    def _packet(self, name: str, payload: bytes, n: int, t0: int, t1: int) -> None:
        body = self._compress(payload)
        offset = self._file.tell()
        self._write_whole(struct.pack("<ii", self._ids[name], len(body)) + body)
        self._table.append((offset + 8, self._ids[name], len(body), n, t0, t1))
        self._last_t[name] = t1

    def write_events(self, events: np.ndarray) -> None:
        """Append events (EVENT_DTYPE, sorted by t) as one packet (split beyond 2^20 events)."""
        if events.dtype != EVENT_DTYPE:
            if events.dtype.names != EVENT_DTYPE.names:
                raise RecordingError(f"write_events needs EVENT_DTYPE, got {events.dtype}", self.path)
            events = as_events(events)  # e.g. the packed layout np.concatenate makes of EVENT_DTYPE
        if not len(events):
            return
        self._check_sorted("events", events["t"])
        for payload, n, t0, t1 in events_payloads(events):
            self._packet("events", payload, n, t0, t1)

    def write_frame(self, frame: Frame) -> None:
        """Append one frame (8- or 16-bit gray or BGR): timestamp = exposure start, SOE/EOE and exposure set."""
        soe = int(frame.exposure_start_us)
        self._check("frames", soe, soe)
        try:
            payload = frame_payload(frame, self._frame_source)
        except ValueError as exc:
            raise RecordingError(str(exc), self.path) from None
        self._packet("frames", payload, 1, soe, soe)

    def write_imu(self, imu: np.ndarray) -> None:
        """Append IMU samples (IMU_DTYPE, sorted by t) as one packet."""
        if not self._accept("imu", imu, IMU_DTYPE, "IMU_DTYPE"):
            return
        payload = imu_payload(imu)
        self._packet("imu", payload, len(imu), int(imu["t"][0]), int(imu["t"][-1]))

    def write_triggers(self, triggers: np.ndarray) -> None:
        """Append triggers (TRIGGER_DTYPE, sorted by t) as one packet."""
        if not self._accept("triggers", triggers, TRIGGER_DTYPE, "TRIGGER_DTYPE"):
            return
        payload = triggers_payload(triggers)
        self._packet("triggers", payload, len(triggers), int(triggers["t"][0]), int(triggers["t"][-1]))

    # ------------------------------------------------------------------------------------------- close
    def flush(self) -> None:
        """Push written packets to the OS, so the file up to here survives a crash of this process (the file is
        unbuffered: each packet already went to the OS as it was written)."""
        if not self._closed:
            try:
                self._file.flush()
            except OSError as exc:
                raise RecordingError(f"cannot write the recording ({exc.strerror or exc})", self.path) from exc

    def close(self) -> None:
        """Write the FileDataTable and patch dataTablePosition. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            dtp = self._file.tell()
            rec = np.zeros(len(self._table), dtype=_FTAB_REC)
            if self._table:
                cols = np.array(self._table, dtype=np.int64)
                for i, name in enumerate(("off", "sid", "size", "n", "t0", "t1")):
                    rec[name] = cols[:, i]
            self._write_whole(self._compress(S.build_table_vector_root(b"FTAB", rec, _FTAB_SLOTS)))
            self._file.seek(self._dtp_pos)
            self._write(struct.pack("<q", dtp))
            self._check_still_there()
        finally:
            self._file.close()

    def _check_still_there(self) -> None:
        """Writes into a file whose name or folder was removed mid-run all succeed (the data go to a nameless
        file that vanishes at close): without this a run reported every frame written to a file that is gone."""
        try:
            here, ours = os.stat(self.path), os.fstat(self._file.fileno())
            same = (here.st_dev, here.st_ino) == (ours.st_dev, ours.st_ino)
        except OSError:
            same = False
        if not same:
            raise RecordingError("the file is no longer there: it or its folder was deleted or moved while it was "
                                 "being written, so nothing written to it is at this path", self.path)

    def __enter__(self) -> "Aedat4Writer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------------------- packet encoding
# Module-level so that every AEDAT4 producer (this file writer, edi_live.dv_output's network server) shares them.

def info_xml(streams: list[tuple[int, str, str]], width: int, height: int, camera_name: str,
             compression: str, color_filter: ColorFilter | None = None) -> bytes:
    """The IOHeader's infoNode XML for `streams` = [(stream id, type identifier, output name), ...]; a frame stream
    of raw Bayer mosaics names their pattern (`color_filter`) in its info node, the key the reader looks for."""
    parts = ['<dv version="2.0">', '<node name="outInfo" path="/outInfo/">']
    for sid, type_id, name in streams:
        base = f"/outInfo/{sid}/"
        parts.append(f'<node name="{sid}" path="{base}">')
        for key, val in (("compression", compression.upper()), ("originalModuleName", "edi-live"),
                         ("originalOutputName", name), ("typeDescription", S.TYPE_DESCRIPTIONS[type_id]),
                         ("typeIdentifier", type_id)):
            parts.append(f'<attr key="{key}" type="string">{escape(val)}</attr>')
        parts.append(f'<node name="info" path="{base}info/">')
        if type_id == "FRME" and color_filter:
            parts.append(f'<attr key="{COLOR_FILTER_KEY}" type="string">{escape(color_filter)}</attr>')
        if type_id in ("EVTS", "FRME"):
            parts.append(f'<attr key="sizeX" type="int">{width}</attr>')
            parts.append(f'<attr key="sizeY" type="int">{height}</attr>')
        parts.append(f'<attr key="source" type="string">{escape(camera_name)}</attr>')
        parts.append("</node></node>")
    parts.append("</node></dv>")
    return "\n".join(parts).encode()


def io_header(compression: str, data_table_position: int, xml: bytes) -> tuple[bytes, dict[int, int]]:
    """The size-prefixed IOHE buffer (what follows the magic line in a file, and opens a network stream)."""
    spec = (S.TableSpec().scalar(S.IOH_COMPRESSION, "i", S.COMPRESSION_CODES[compression])
            .scalar(S.IOH_DATA_TABLE_POSITION, "q", data_table_position).string(S.IOH_INFO_NODE, xml))
    return S.build_root(b"IOHE", spec)


def events_payloads(events: np.ndarray):
    """(EVTS payload, count, first t, last t) per chunk of at most MAX_EVENTS_PER_PACKET events (EVENT_DTYPE)."""
    for i in range(0, len(events), MAX_EVENTS_PER_PACKET):
        chunk = np.ascontiguousarray(events[i:i + MAX_EVENTS_PER_PACKET])
        raw = chunk.view(np.uint8).reshape(-1, 16).copy()
        raw[:, 12] = chunk["p"]  # polarity byte 0/1, padding zeroed
        raw[:, 13:] = 0
        spec = S.TableSpec().vector_bytes(0, raw.tobytes(), len(chunk), align=8)
        payload, _ = S.build_root(b"EVTS", spec)
        yield payload, len(chunk), int(chunk["t"][0]), int(chunk["t"][-1])


def frame_payload(frame: Frame, source_code: int) -> bytes:
    """FRME payload of an 8- or 16-bit gray or BGR frame (DV's colour frame format, OpenCV's 8UC3/16UC3):
    timestamp = exposure start, SOE/EOE and exposure set. ValueError for another pixel type."""
    img = np.ascontiguousarray(frame.image)
    colour = img.ndim == 3
    if img.dtype == np.uint8:
        fmt = S.FRAME_FORMAT_BGR8 if colour else S.FRAME_FORMAT_GRAY8
    elif img.dtype == np.uint16:
        fmt, img = S.FRAME_FORMAT_BGR16 if colour else S.FRAME_FORMAT_GRAY16, img.astype("<u2", copy=False)
    else:
        raise ValueError(f"frames must be uint8 or uint16 gray or BGR, got {img.dtype}")
    h, w = img.shape[:2]
    soe, eoe = int(frame.exposure_start_us), int(frame.exposure_end_us)
    spec = (S.TableSpec().scalar(S.FR_TIMESTAMP, "q", soe)
            .scalar(S.FR_SOF, "q", int(frame.start_us or 0)).scalar(S.FR_EOF, "q", int(frame.end_us or 0))
            .scalar(S.FR_SOE, "q", soe).scalar(S.FR_EOE, "q", eoe)
            .scalar(S.FR_FORMAT, "b", fmt).scalar(S.FR_SIZE_X, "h", w).scalar(S.FR_SIZE_Y, "h", h)
            .scalar(S.FR_POS_X, "h", 0).scalar(S.FR_POS_Y, "h", 0)
            .vector_bytes(S.FR_PIXELS, img.tobytes(), img.nbytes, align=1)
            .scalar(S.FR_EXPOSURE, "q", eoe - soe).scalar(S.FR_SOURCE, "b", source_code))
    payload, _ = S.build_root(b"FRME", spec)
    return payload


def imu_payload(imu: np.ndarray) -> bytes:
    """IMUS payload of IMU samples (IMU_DTYPE)."""
    rec = np.zeros(len(imu), dtype=_IMU_REC)
    rec["t"] = imu["t"]
    rec["f"][:, 0] = imu["temperature_c"]
    rec["f"][:, 1:4], rec["f"][:, 4:7], rec["f"][:, 7:10] = imu["accel_g"], imu["gyro_dps"], imu["mag_ut"]
    return S.build_table_vector_root(b"IMUS", rec, _IMU_SLOTS)


def triggers_payload(triggers: np.ndarray) -> bytes:
    """TRIG payload of triggers (TRIGGER_DTYPE)."""
    rec = np.zeros(len(triggers), dtype=_TRIG_REC)
    rec["t"], rec["type"] = triggers["t"], triggers["type"]
    return S.build_table_vector_root(b"TRIG", rec, _TRIG_SLOTS)
