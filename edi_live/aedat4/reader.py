"""Streaming AEDAT 4.0 reader: one packet in memory at a time.

Owns: the file (opening, chunked reads into one reused buffer), packet walking (decompression in `compression`),
dispatching payloads to their decoders (EVTS and FRME in `decode`, IMUS and TRIG in `payloads`), and the
FileDataTable (`datatable`). The file head is parsed by `header`. Packets come out in file order (arrival order,
not time order; `drivers.replay` merges them).

Damage policy, the same for every kind of damage (a cut, a flipped byte, a corrupt stream id or size, a damaged
FileDataTable, ...): everything before the damage is yielded, then one `RecordingError` names the file, the byte
offset and what is wrong. Nothing is skipped in silence and nothing is only warned about; the CLI turns the error
into `edi-live: error: FILE at byte N: ...` and exit 1 after the data before it was processed. A packet whose stream
id the header does not declare is such damage. Streams the header declares with a type edi-live does not decode
(e.g. bounding boxes) are not damage: they are announced once on the log and skipped.
"""

from __future__ import annotations

import array
import io
import logging
import os
import struct
from typing import Iterable, Iterator

import numpy as np

from edi_live.aedat4 import schema as S
from edi_live.aedat4.compression import decompressor
from edi_live.aedat4.datatable import DATA_TABLE_DTYPE, parse_data_table
from edi_live.aedat4._check import parse_check_evts
from edi_live.aedat4.decode import NO_EVENTS, decode_events, decode_frame
from edi_live.aedat4.header import SUPPORTED_TYPES, StreamInfo, read_header, split_camera_label
from edi_live.aedat4.payloads import decode_imu, decode_triggers
from edi_live.datatypes import EVENT_DTYPE
from edi_live.errors import RecordingError, ResourceError

__all__ = ["Aedat4Reader", "StreamInfo", "DATA_TABLE_DTYPE", "SUPPORTED_TYPES", "split_camera_label", "READ_CHUNK"]

log = logging.getLogger(__name__)

READ_CHUNK = 1 << 20
_PH = struct.Struct("<ii")


class Aedat4Reader:
    """Streaming AEDAT4 reader; a context manager. Iterate for `(StreamInfo, data)` in file order.

    data is an events ndarray (EVENT_DTYPE, a read-only view of the decompressed packet), a `Frame`, an IMU ndarray
    (IMU_DTYPE) or a triggers ndarray (TRIGGER_DTYPE). Iterating again starts from the first packet. A pass that
    reaches the end of the packets also checks the FileDataTable (when the file has one).
    """

    def __init__(self, path: str | os.PathLike, *, validate: bool = True) -> None:
        self.path = os.fspath(path)
        self.validate = validate
        try:
            self._file = open(self.path, "rb", buffering=0)  # unbuffered: packets() reads large chunks itself
        except OSError as exc:
            raise RecordingError(f"cannot open the recording ({exc.strerror or exc})", self.path) from exc
        try:
            self.file_size = os.fstat(self._file.fileno()).st_size
            head = read_header(self._read_at, self.file_size, self.path)
        except BaseException:
            self._file.close()
            raise
        self._adopt(head)

    def _adopt(self, head) -> None:
        """Take the parsed file head (header.read_header) as this reader's attributes."""
        self.data_start = head.data_start
        self.compression = head.compression
        self.data_table_position = head.data_table_position
        self._end = head.end
        self._table_beyond_end = head.table_beyond_end
        self.streams = head.streams
        self.source_info = head.source_info
        self._by_id = {s.id: s for s in self.streams}
        for s in self.streams:
            if not s.supported:
                log.warning("%s: stream %d '%s' has type %s, which edi-live does not read; its packets are skipped",
                            self.path, s.id, s.name, s.type)
        self._buffer: memoryview | None = None
        self._buffer_busy = False

    def _error(self, message: str, offset: int | None) -> RecordingError:
        return RecordingError(message, self.path, offset)

    # ------------------------------------------------------------------------------------------ packets
    def packets(self, types: Iterable[str] | None = None) -> Iterator[tuple[StreamInfo, int, bytes]]:
        """Raw packets in file order: (stream, file offset of the packet header, decompressed payload).

        Packets of declared streams of unsupported types are skipped, and so, without being decompressed, are
        packets whose type is not in `types` (when given, e.g. ("EVTS",)). Ends with the table check.
        """
        end, pos = self._end, self.data_start
        # The file is read in chunks of READ_CHUNK bytes (or one packet, if larger) into one reused buffer, and
        # packets are decompressed straight from memoryviews of it: one read per many packets, no allocation per
        # read, and never more than one chunk in memory. A payload never points into the buffer (decompression and
        # the NONE path both produce new bytes), so overwriting it on the next read is safe. The buffer is kept for
        # the next pass; a second pass running interleaved with this one gets its own (every read seeks first).
        shared = not self._buffer_busy
        view = self._buffer if shared and self._buffer is not None else \
            memoryview(bytearray(max(8, min(READ_CHUNK, end - pos))))
        if shared:
            self._buffer, self._buffer_busy = view, True
        walked = array.array("q")  # offset, size of every packet, flat, for the table check (cheaper than tuples)
        try:
            yield from self._walk(view, pos, end, types, shared, walked)
        finally:
            if shared:
                self._buffer_busy = False
        if self._table_beyond_end:
            raise self._error(f"the FileDataTable should start at byte {self.data_table_position} but the file ends "
                              f"at byte {self.file_size} (truncated)", self.file_size)
        self._check_table(walked)

    def _check_table(self, walked: array.array) -> None:
        """Damage in the FileDataTable is reported like damage anywhere else: it must parse and list exactly the
        packets the file holds (DV, aestream, evlib and our writer all list every packet in file order). Stream
        ids are not compared: a wrong one in a packet header is caught by its payload's FlatBuffer identifier."""
        table = self.data_table()
        if table is None:
            return
        found = np.frombuffer(walked, dtype=np.int64).reshape(-1, 2) if walked else np.zeros((0, 2), np.int64)
        listed = np.stack([table["byte_offset"] - 8, table["size"]], axis=1).astype(np.int64)
        if found.shape != listed.shape or not np.array_equal(found, listed):
            n = min(len(found), len(listed))
            k = int(np.flatnonzero((found[:n] != listed[:n]).any(axis=1))[0]) if n and not np.array_equal(
                found[:n], listed[:n]) else n
            raise self._error(f"the FileDataTable lists {len(listed)} packets but the file holds {len(found)}; they "
                              f"first differ at packet {k} (a damaged table)", self.data_table_position)

    def _walk(self, view: memoryview, pos: int, end: int, types: Iterable[str] | None, shared: bool,
              walked: array.array) -> Iterator[tuple[StreamInfo, int, bytes]]:
        unpack_from = _PH.unpack_from
        note = walked.extend
        decompress = decompressor(self.compression)
        by_id = self._by_id
        wanted = None if types is None else {s.id for s in self.streams if s.type in set(types)}
        buf = view.obj
        base, filled = pos, 0
        while pos < end:
            rel = pos - base
            if rel + 8 > filled:
                if end - pos < 8:
                    raise self._error(f"the file ends inside a packet header ({end - pos} of 8 bytes; truncated)",
                                      pos)
                view, filled = self._fill(view, pos, 8)
                buf, base, rel = view.obj, pos, 0
            sid, size = unpack_from(buf, rel)
            if size <= 0:
                raise self._error(f"corrupt packet header (size {size})", pos)
            if pos + 8 + size > end:
                what = "the FileDataTable" if end == self.data_table_position else "the end of the file"
                why = "corrupt size or table position" if end == self.data_table_position else "truncated"
                raise self._error(f"packet of {size} bytes runs past {what}, which is at byte {end} ({why})", pos)
            note((pos, size))
            stream = by_id.get(sid)
            if stream is None:
                raise self._error(f"packet of {size} bytes belongs to stream {sid}, which the header does not "
                                  f"declare (declared: {sorted(by_id)}; a corrupt stream id)", pos)
            if not stream.supported or (wanted is not None and sid not in wanted):
                pos += 8 + size
                continue
            if rel + 8 + size > filled:
                view, filled = self._fill(view, pos, 8 + size)
                buf, base, rel = view.obj, pos, 0
                if shared:
                    self._buffer = view  # grown for a large packet: keep the larger one
            try:
                payload = decompress(view[rel + 8:rel + 8 + size])
            except Exception as exc:  # lz4/zstandard raise their own types (RuntimeError, ZstdError, ...)
                raise self._error(f"packet of stream {sid} does not decompress as {self.compression.upper()} "
                                  f"({exc})", pos) from None
            yield stream, pos, payload
            pos += 8 + size

    def _read_at(self, pos: int, size: int) -> bytes:
        """Up to `size` bytes from `pos` (fewer only at the end of the file)."""
        self._file.seek(pos)
        parts, got = [], 0
        while got < size:
            chunk = self._file.read(size - got)
            if not chunk:
                break
            parts.append(chunk)
            got += len(chunk)
        return b"".join(parts)

    def _fill(self, view: memoryview, pos: int, need: int) -> tuple[memoryview, int]:
        """Read from `pos` into the buffer behind `view` (a larger one when `need` exceeds it): at least `need` bytes
        (the caller checked they exist), at most the buffer size. Returns (view of the buffer, bytes filled)."""
        if need > len(view):
            view = memoryview(bytearray(need))
        want = min(len(view), self._end - pos)
        self._file.seek(pos)
        got = 0
        while got < want:  # a raw file may return short reads
            k = self._file.readinto(view[got:want])
            if not k:
                break
            got += k
        if got < need:
            raise self._error("the file is shorter than its size on disk (read failed)", pos)
        return view, got

    # ---------------------------------------------------------------------------------------- decoding
    def __iter__(self) -> Iterator[tuple[StreamInfo, object]]:
        for stream, _, data in self.records():
            yield stream, data

    def records(self, types: Iterable[str] | None = None) -> Iterator[tuple[StreamInfo, int, object]]:
        """Like iteration, with the file offset of each packet: (stream, offset, data); `types` as in packets()."""
        seqs: dict[int, int] = {}
        for stream, pos, payload in self.packets(types):
            seq = 0
            if stream.type == "FRME":
                seq = seqs.get(stream.id, 0)
                seqs[stream.id] = seq + 1
            yield stream, pos, self.decode_payload(stream, pos, payload, seq)

    def decode_payload(self, stream: StreamInfo, pos: int, payload: bytes, seq: int = 0) -> object:
        """One decompressed packet of `stream` as events, a Frame (numbered `seq`), IMU or triggers; any defect
        is a RecordingError at byte `pos`. Also used for network streams (see `from_stream_header`)."""
        try:
            t = stream.type
            if t == "EVTS":
                return decode_events(payload, stream, self.validate)
            if t == "FRME":
                return decode_frame(payload, stream, seq)
            if t == "IMUS":
                return decode_imu(payload)
            return decode_triggers(payload)
        except RecordingError as exc:
            raise self._error(str(exc), pos) from None
        except S.FlatBufferError as exc:
            raise self._error(f"corrupt {stream.type} packet: {exc} (payload byte {exc.pos})", pos) from None
        except (MemoryError, OSError) as exc:  # this process's limits (memory, open files): not the file's fault
            raise ResourceError(f"{self.path}: cannot decode its {stream.type} packet at byte {pos} "
                                f"({type(exc).__name__}: {exc}): a limit of this process, not damage in the file") from exc
        except Exception as exc:  # anything else a damaged payload provokes (struct, numpy, ...) is the same fault
            raise self._error(f"corrupt {stream.type} packet ({type(exc).__name__}: {exc})", pos) from exc

    @classmethod
    def from_stream_header(cls, header: bytes, where: str) -> "Aedat4Reader":
        """A reader for an AEDAT4 network stream, which is a file without the magic line and the data table:
        `header` is the size-prefixed IOHeader the server sends first; `where` names the stream in errors.
        Only the header attributes and `decode_payload()` are meant for use (there is no file to walk)."""
        self = cls.__new__(cls)
        self.path, self.validate = where, True
        self._file = io.BytesIO(S.MAGIC + bytes(header))
        self.file_size = len(S.MAGIC) + len(header)
        self._adopt(read_header(self._read_at, self.file_size, self.path))
        return self

    def events(self) -> Iterator[np.ndarray]:
        """Only the event arrays, in file order (other packets are skipped undecompressed): the fast path.

        The plain, valid EVTS layout is parsed and checked in one compiled call inline here (DV's 1 ms packets are
        small, so per-packet Python calls are a large share of the time); anything else goes to `decode_events`,
        which yields the same arrays or produces the precise error."""
        validate = self.validate
        frombuffer, u8, dtype, none = np.frombuffer, np.uint8, EVENT_DTYPE, NO_EVENTS
        parse_check = parse_check_evts
        for stream, pos, payload in self.packets(("EVTS",)):
            if validate:
                start, count, _, why = parse_check(frombuffer(payload, u8), stream.width, stream.height)
                if start >= 0 and not why:
                    yield frombuffer(payload, dtype, count, start) if count else none
                    continue
            try:
                ev = decode_events(payload, stream, validate)
            except RecordingError as exc:
                raise self._error(str(exc), pos) from None
            except S.FlatBufferError as exc:
                raise self._error(f"corrupt EVTS packet: {exc} (payload byte {exc.pos})", pos) from None
            yield ev

    # ------------------------------------------------------------------------------------- data table
    def data_table(self) -> np.ndarray | None:
        """The FileDataTable as a DATA_TABLE_DTYPE array (missing fields are 0), or None when the file has none."""
        dtp = self.data_table_position
        if dtp < 0 or self._table_beyond_end:
            return None
        body = self._read_at(dtp, self.file_size - dtp)
        try:
            payload = decompressor(self.compression)(body)
        except Exception as exc:
            raise self._error(f"the FileDataTable does not decompress ({exc}; damaged or truncated)", dtp) from None
        try:
            return parse_data_table(payload)
        except S.FlatBufferError as exc:
            raise self._error(f"corrupt FileDataTable: {exc}", dtp) from None
        except Exception as exc:  # whatever else a damaged table provokes is the same fault
            raise self._error(f"corrupt FileDataTable ({type(exc).__name__}: {exc})", dtp) from exc

    def time_range(self) -> tuple[int, int] | None:
        """(first, last) timestamp in µs from the FileDataTable, or None when the table lacks timestamps."""
        table = self.data_table()
        if table is None or not len(table) or not table["t_end"].any():
            return None
        valid = table[table["t_end"] != 0]
        return int(valid["t_start"].min()), int(valid["t_end"].max())

    # -------------------------------------------------------------------------------------- lifecycle
    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "Aedat4Reader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
