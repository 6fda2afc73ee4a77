"""The head of an AEDAT 4.0 file: the magic line, the IOHeader FlatBuffer (parsed through its vtable, never fixed
offsets) and its infoNode XML (streams, resolution, camera).

`read_header(read_at, file_size, path)` returns a `Header`; every defect is a `RecordingError` naming the file and
byte offset. Streams of types edi-live does not decode are listed (and announced once by the reader), not refused.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Callable

from edi_live.aedat4 import schema as S
from edi_live.datatypes import COLOR_FILTERS, ColorFilter, SourceInfo
from edi_live.errors import RecordingError

SUPPORTED_TYPES = ("EVTS", "FRME", "IMUS", "TRIG")
STREAM_NAMES = {"EVTS": "events", "FRME": "frames", "IMUS": "imu", "TRIG": "triggers"}
"""Each supported stream type identifier as a user names it (the DV network input's endpoint prefixes)."""

MAX_SENSOR_SIDE = 8192
"""Sensor sides above this are refused as a damaged header (the largest event cameras are 1280 wide)."""

_I32, _I64 = struct.Struct("<i"), struct.Struct("<q")


@dataclass(frozen=True)
class StreamInfo:
    """One stream declared in the header XML."""

    id: int
    type: str  # typeIdentifier: "EVTS", "FRME", "IMUS", "TRIG" or something unsupported
    name: str = ""  # originalOutputName, e.g. "events"
    width: int = 0  # sizeX (events and frames only; 0 when not given)
    height: int = 0
    source: str = ""  # camera, e.g. "DAVIS346_00000391"
    compression: str = ""
    color_filter: ColorFilter | None = None  # a frame stream of raw Bayer mosaics: their pattern (info "colorFilter")

    @property
    def supported(self) -> bool:
        return self.type in SUPPORTED_TYPES


@dataclass(frozen=True)
class Header:
    data_start: int  # first packet header
    compression: str  # "none", "lz4", "lz4_high", "zstd", "zstd_high"
    data_table_position: int  # byte offset of the FileDataTable, -1 when the file has none
    end: int  # where the packets end: the table position when it lies in the file, else the file size
    table_beyond_end: bool  # the table should start after the end of the file (a truncated file)
    streams: list[StreamInfo]
    source_info: SourceInfo


def split_camera_label(label: str) -> tuple[str, str]:
    """'DAVIS346_00000391' -> ('DAVIS346', '00000391'); a label without '_<digits>' is all name."""
    head, sep, tail = label.rpartition("_")
    if sep and head and tail.isdigit():
        return head, tail
    return (label or "unknown"), ""


def read_header(read_at: Callable[[int, int], bytes], file_size: int, path: str) -> Header:
    """Parse the file head; `read_at(pos, size)` returns up to `size` bytes from `pos`."""

    def error(message: str, offset: int | None) -> RecordingError:
        return RecordingError(message, path, offset)

    if file_size == 0:
        raise error("the file is empty, not an AEDAT4 recording", 0)
    head = read_at(0, S.HEADER_START + 4)
    if not head.startswith(S.MAGIC):
        if S.MAGIC.startswith(head):
            raise error("the file ends inside the AEDAT4 magic line (truncated)", len(head))
        if head.startswith(b"#!AER-DAT"):
            version = head[9:12].decode("ascii", "replace")
            raise error(f"AEDAT {version} is not supported; only AEDAT 4.0 files can be read", 0)
        raise error("not an AEDAT4 recording (the file does not start with '#!AER-DAT4.0')", 0)
    if len(head) < S.HEADER_START + 4:
        raise error("the file ends inside the header (truncated)", len(head))
    n = struct.unpack_from("<I", head, S.HEADER_START)[0]
    data_start = S.HEADER_START + 4 + n
    if data_start > file_size:
        raise error(f"the header claims {n} bytes but the file ends at byte {file_size} (truncated)", S.HEADER_START)
    buf = head[S.HEADER_START:] + read_at(S.HEADER_START + 4, n)
    try:
        root = S.root_table(buf, b"IOHE")
        code_pos = root.field_pos(S.IOH_COMPRESSION, 4)
        code = _I32.unpack_from(buf, code_pos)[0] if code_pos else 0
        dtp = root.scalar(S.IOH_DATA_TABLE_POSITION, _I64, -1)
        xml = root.string(S.IOH_INFO_NODE)
    except S.FlatBufferError as exc:
        raise error(f"corrupt IOHeader: {exc}", S.HEADER_START + exc.pos) from None
    if code not in S.COMPRESSION_NAMES:
        raise error(f"unknown compression type {code} (known: 0-4)", S.HEADER_START + code_pos)
    if 0 <= dtp < data_start:
        raise error(f"dataTablePosition {dtp} points into the header", S.HEADER_START)
    streams = _parse_xml(xml, error)
    return Header(data_start=data_start, compression=S.COMPRESSION_NAMES[code], data_table_position=dtp,
                  end=dtp if 0 <= dtp <= file_size else file_size, table_beyond_end=dtp > file_size,
                  streams=streams, source_info=_source_info(streams))


def _parse_xml(xml: bytes, error: Callable[[str, int | None], RecordingError]) -> list[StreamInfo]:
    if not xml:
        return []
    try:
        root = ET.fromstring(xml.decode("utf-8", "replace"))
    except ET.ParseError as exc:
        raise error(f"the stream description (infoNode XML) is malformed: {exc}", S.HEADER_START) from None
    streams = []
    for node in root.iter("node"):
        attrs = {a.get("key"): (a.text or "") for a in node.findall("attr")}
        if "typeIdentifier" not in attrs:
            continue
        try:
            sid = int(node.get("name", ""))
        except ValueError:
            continue
        info = node.find("node[@name='info']")
        iattrs = {a.get("key"): (a.text or "") for a in info.findall("attr")} if info is not None else {}
        width, height = _int(iattrs.get("sizeX")), _int(iattrs.get("sizeY"))
        if max(width, height) > MAX_SENSOR_SIDE:  # its buffers would be allocated before anything else failed
            raise error(f"the stream description declares a {width}x{height} sensor, larger than any event camera "
                        f"(at most {MAX_SENSOR_SIDE} pixels a side are read): a damaged header?", S.HEADER_START)
        streams.append(StreamInfo(id=sid, type=attrs["typeIdentifier"].strip(),
                                  name=attrs.get("originalOutputName", "").strip() or f"stream{sid}",
                                  width=width, height=height,
                                  source=iattrs.get("source", "").strip(),
                                  compression=attrs.get("compression", "").strip(),
                                  color_filter=color_filter_of_metadata(iattrs.get(COLOR_FILTER_KEY))))
    return streams


# A frame stream holds raw Bayer mosaics when its info node says so with the attribute "colorFilter" (the key
# dv-processing's writers store with Config.addStreamMetadata("frames", ("colorFilter", ...)); DV itself writes a
# colour DAVIS's frames demosaiced, as BGR). Accepted values: our names (row by row: RGGB, GRBG, GBRG, BGGR),
# libcaer's (clockwise from the top-left: RGBG, GRGB, GBGR, BGRG, see drivers.davis.models) or libcaer's code
# 0-4; anything else, or MONO/0, reads as mono.
COLOR_FILTER_KEY = "colorFilter"
_LIBCAER_NAMES = {"RGBG": "RGGB", "GRGB": "GRBG", "GBGR": "GBRG", "BGRG": "BGGR"}
_LIBCAER_CODES = {"1": "RGGB", "2": "GRBG", "3": "GBRG", "4": "BGGR"}


def color_filter_of_metadata(value: str | None) -> ColorFilter | None:
    v = (value or "").strip().upper()
    if v in COLOR_FILTERS:
        return v  # type: ignore[return-value]
    return _LIBCAER_NAMES.get(v) or _LIBCAER_CODES.get(v)  # type: ignore[return-value]


def _source_info(streams: list[StreamInfo]) -> SourceInfo:
    ranked = sorted(streams, key=lambda s: (s.type != "EVTS", s.type != "FRME", s.id))
    sized = [s for s in ranked if s.width > 0 and s.height > 0]
    label = next((s.source for s in ranked if s.source), "")
    name, serial = split_camera_label(label)
    w, h = (sized[0].width, sized[0].height) if sized else (0, 0)
    pattern = next((s.color_filter for s in ranked if s.type == "FRME" and s.color_filter), None)
    return SourceInfo(width=w, height=h, name=name, serial=serial, kind="replay", color_filter=pattern)


def _int(text: str | None) -> int:
    try:
        return max(0, int((text or "0").strip()))
    except ValueError:
        return 0
