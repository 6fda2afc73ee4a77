"""AEDAT 4.0 wire facts and a minimal FlatBuffers codec (hand-written: struct + numpy, no `flatbuffers` package).

Owns: the constants of the format (magic, compression codes, type identifiers, vtable slot numbers), bounds-checked
table/vtable access for reading, and a small forward builder for writing size-prefixed buffers. Every
FlatBuffers table is located through its vtable, never through fixed offsets. Malformed buffers raise
`FlatBufferError`; the reader turns that into a `RecordingError` naming the file and byte offset.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

MAGIC = b"#!AER-DAT4.0\r\n"
HEADER_START = len(MAGIC)  # the IOHeader's u32 size prefix sits here

COMPRESSION_CODES = {"none": 0, "lz4": 1, "lz4_high": 2, "zstd": 3, "zstd_high": 4}
COMPRESSION_NAMES = {v: k for k, v in COMPRESSION_CODES.items()}

# IOHeader slots
IOH_COMPRESSION, IOH_DATA_TABLE_POSITION, IOH_INFO_NODE = 0, 1, 2
# Frame table slots (13-slot schema; older writers stop at slot 10)
FR_TIMESTAMP, FR_SOF, FR_EOF, FR_SOE, FR_EOE = 0, 1, 2, 3, 4
FR_FORMAT, FR_SIZE_X, FR_SIZE_Y, FR_POS_X, FR_POS_Y, FR_PIXELS, FR_EXPOSURE, FR_SOURCE = 5, 6, 7, 8, 9, 10, 11, 12
FRAME_FORMAT_GRAY8, FRAME_FORMAT_GRAY16 = 0, 2
FRAME_FORMAT_BGR8, FRAME_FORMAT_BGR16 = 16, 18  # OpenCV 8UC3 / 16UC3: DV's colour frames
FRAME_FORMAT_CHANNELS = {0: (1, 1), 2: (1, 2), 16: (3, 1), 18: (3, 2), 24: (4, 1), 26: (4, 2)}  # (channels, bytes)
FRAME_SOURCES = {"undefined": 0, "sensor": 1, "aps": 1, "accumulation": 2, "motion_compensation": 3,
                 "synthetic": 4, "reconstruction": 5, "visualization": 6, "other": 7}

EVENT_RECORD_BYTES = 16
TYPE_DESCRIPTIONS = {
    "EVTS": "Array of events (polarity ON/OFF).",
    "FRME": "Standard frame (8-bit image).",
    "IMUS": "Inertial Measurement Unit data samples.",
    "TRIG": "External triggers and special signals.",
}


class FlatBufferError(ValueError):
    """A FlatBuffer is malformed; `pos` is the offending position inside the buffer."""

    def __init__(self, message: str, pos: int = 0) -> None:
        super().__init__(message)
        self.pos = pos


_U16 = struct.Struct("<H")
_I32 = struct.Struct("<i")
_U32 = struct.Struct("<I")
_I64 = struct.Struct("<q")


class Table:
    """A FlatBuffers table inside `buf` at `pos`, with bounds-checked access to its fields by slot."""

    __slots__ = ("buf", "pos", "_vt", "_vt_len")

    def __init__(self, buf, pos: int) -> None:
        n = len(buf)
        if pos < 0 or pos + 4 > n:
            raise FlatBufferError("table offset outside the buffer", pos)
        vt = pos - _I32.unpack_from(buf, pos)[0]
        if vt < 0 or vt + 4 > n or vt % 2:
            raise FlatBufferError("vtable offset outside the buffer", pos)
        vt_len = _U16.unpack_from(buf, vt)[0]
        if vt_len < 4 or vt_len % 2 or vt + vt_len > n:
            raise FlatBufferError("bad vtable size", vt)
        self.buf, self.pos, self._vt, self._vt_len = buf, pos, vt, vt_len

    def field_pos(self, slot: int, size: int) -> int:
        """Absolute position of a field of `size` bytes, or 0 when the field is absent."""
        entry = 4 + 2 * slot
        if entry + 2 > self._vt_len:
            return 0
        off = _U16.unpack_from(self.buf, self._vt + entry)[0]
        if off == 0:
            return 0
        p = self.pos + off
        if p + size > len(self.buf):
            raise FlatBufferError(f"field {slot} outside the buffer", p)
        return p

    def scalar(self, slot: int, fmt: struct.Struct, default=0):
        p = self.field_pos(slot, fmt.size)
        return fmt.unpack_from(self.buf, p)[0] if p else default

    def _indirect(self, slot: int) -> int:
        p = self.field_pos(slot, 4)
        if not p:
            return 0
        target = p + _U32.unpack_from(self.buf, p)[0]
        if target + 4 > len(self.buf):
            raise FlatBufferError(f"offset of field {slot} points outside the buffer", p)
        return target

    def vector(self, slot: int, elem_size: int) -> tuple[int, int]:
        """(position of the first element, element count) of a vector field; (0, 0) when absent."""
        v = self._indirect(slot)
        if not v:
            return 0, 0
        count = _U32.unpack_from(self.buf, v)[0]
        if v + 4 + count * elem_size > len(self.buf):
            raise FlatBufferError(f"vector of field {slot} runs past the buffer ({count} elements)", v)
        return v + 4, count

    def string(self, slot: int) -> bytes:
        start, count = self.vector(slot, 1)
        return bytes(self.buf[start:start + count]) if count else b""

    def table(self, slot: int) -> "Table | None":
        v = self._indirect(slot)
        return Table(self.buf, v) if v else None


def root_table(buf, identifier: bytes | None, size_prefixed: bool = True) -> Table:
    """The root table of a (size-prefixed) FlatBuffer, checking the 4-byte file identifier when given."""
    base = 4 if size_prefixed else 0
    if len(buf) < base + 8:
        raise FlatBufferError("buffer too short for a FlatBuffer", 0)
    if size_prefixed:
        declared = _U32.unpack_from(buf, 0)[0]
        if declared + 4 > len(buf):
            raise FlatBufferError(f"size prefix {declared} exceeds the buffer ({len(buf)} bytes)", 0)
    if identifier is not None and bytes(buf[base + 4:base + 8]) != identifier:
        found = bytes(buf[base + 4:base + 8])
        raise FlatBufferError(f"identifier {found!r} is not {identifier!r}", base + 4)
    return Table(buf, base + _U32.unpack_from(buf, base)[0])


# ---------------------------------------------------------------------------------------------- writing


@dataclass
class _Field:
    slot: int
    fmt: str  # struct code: q, i, h, b, B, f, or "off" for an offset to out-of-line data
    value: object = 0
    blob: bytes = b""  # for "off": the out-of-line object (vector/string with its u32 length already in front)
    blob_align: int = 4  # alignment of the blob's element data (after the u32 length)


@dataclass
class TableSpec:
    fields: list[_Field] = field(default_factory=list)

    def scalar(self, slot: int, fmt: str, value) -> "TableSpec":
        self.fields.append(_Field(slot, fmt, value))
        return self

    def vector_bytes(self, slot: int, data: bytes | memoryview, count: int, align: int = 4) -> "TableSpec":
        self.fields.append(_Field(slot, "off", blob=_U32.pack(count) + bytes(data), blob_align=align))
        return self

    def string(self, slot: int, text: bytes) -> "TableSpec":
        self.fields.append(_Field(slot, "off", blob=_U32.pack(len(text)) + text + b"\0", blob_align=1))
        return self


def _pad_to(buf: bytearray, align: int, phase: int = 0) -> None:
    """Pad so that len(buf) % align == phase."""
    while len(buf) % align != phase % align:
        buf.append(0)


def build_root(identifier: bytes, spec: TableSpec) -> tuple[bytes, dict[int, int]]:
    """A size-prefixed FlatBuffer holding one root table, written front to back.

    Every listed field is stored (defaults too), so fields can be patched in place later. Returns the buffer and
    each scalar slot's absolute position in it. Scalars are aligned relative to the buffer start, which is how
    FlatBuffers aligns a size-prefixed buffer.
    """
    nslots = max(f.slot for f in spec.fields) + 1
    buf = bytearray(12)
    buf[8:12] = identifier
    vt_pos = len(buf)
    vt_len = 4 + 2 * nslots
    buf += bytes(vt_len)
    # table: soffset at T with T % 8 == 4, so 8-byte fields that follow it are 8-aligned
    _pad_to(buf, 8, 4)
    table_pos = len(buf)
    buf += _I32.pack(table_pos - vt_pos)
    slot_off: dict[int, int] = {}
    positions: dict[int, int] = {}
    order = sorted(spec.fields, key=lambda f: -(4 if f.fmt == "off" else struct.calcsize(f.fmt)))
    for f in order:
        size = 4 if f.fmt == "off" else struct.calcsize("<" + f.fmt)
        _pad_to(buf, size)
        positions[f.slot] = len(buf)
        slot_off[f.slot] = len(buf) - table_pos
        buf += bytes(size) if f.fmt == "off" else struct.pack("<" + f.fmt, f.value)
    table_len = len(buf) - table_pos
    for f in order:
        if f.fmt != "off":
            continue
        # the u32 length sits 4-aligned and the element data after it is blob_align-aligned
        _pad_to(buf, max(4, f.blob_align), (max(4, f.blob_align) - 4) % max(4, f.blob_align))
        obj = len(buf)
        buf += f.blob
        struct.pack_into("<I", buf, positions[f.slot], obj - positions[f.slot])
    _pad_to(buf, 8)
    struct.pack_into("<HH", buf, vt_pos, vt_len, table_len)
    for slot, off in slot_off.items():
        struct.pack_into("<H", buf, vt_pos + 4 + 2 * slot, off)
    struct.pack_into("<II", buf, 0, len(buf) - 4, table_pos - 4)
    return bytes(buf), {s: p for s, p in positions.items()}


def build_table_vector_root(identifier: bytes, records, slot_offsets: list[int]) -> bytes:
    """A size-prefixed FlatBuffer whose root table has one field, slot 0: a vector of tables.

    `records` is a numpy structured array, one inline table per element: its first 4 bytes are the table's
    soffset (filled in here) and its itemsize is a multiple of 8, so each table starts at a position = 4 mod 8
    and its 8-byte fields are 8-aligned. All elements share one vtable with `slot_offsets[slot]` = the byte
    offset of that slot inside the record (0 = absent).
    """
    import numpy as np

    n = len(records)
    item = records.dtype.itemsize
    if item % 8:
        raise ValueError("record itemsize must be a multiple of 8")
    buf = bytearray(12)
    buf[8:12] = identifier
    buf += struct.pack("<HHH", 6, 8, 4)  # root vtable at 12: one offset field at table offset 4
    _pad_to(buf, 8, 4)
    root = len(buf)
    buf += _I32.pack(root - 12) + bytes(4)
    evt = len(buf)
    buf += struct.pack(f"<HH{len(slot_offsets)}H", 4 + 2 * len(slot_offsets), item, *slot_offsets)
    _pad_to(buf, 4)
    vec = len(buf)
    struct.pack_into("<I", buf, root + 4, vec - (root + 4))
    buf += _U32.pack(n) + bytes(4 * n)
    _pad_to(buf, 8, 4)
    first = len(buf)
    table_pos = first + item * np.arange(n, dtype=np.int64)
    entries = (table_pos - (vec + 4 + 4 * np.arange(n, dtype=np.int64))).astype("<u4")
    buf[vec + 4:vec + 4 + 4 * n] = entries.tobytes()
    recs = np.ascontiguousarray(records).copy()
    if n:
        recs[recs.dtype.names[0]] = table_pos - evt
    buf += recs.tobytes()
    _pad_to(buf, 8)
    struct.pack_into("<II", buf, 0, len(buf) - 4, root - 4)
    return bytes(buf)


def table_vector_fields(buf, vec_start: int, count: int, slots: dict[int, str]):
    """Read scalar fields of every table in a vector of tables, vectorised with numpy.

    `slots` maps slot -> numpy dtype string (e.g. "<i8", "<f4", "i1"). Returns slot -> array of `count` values
    (0 where a table lacks the field). Tables may share vtables (DV writers do) or not; each distinct vtable is
    parsed once. Bounds are checked for every element.
    """
    import numpy as np

    n = len(buf)
    raw = np.frombuffer(buf, dtype=np.uint8)
    out = {slot: np.zeros(count, dtype=dt) for slot, dt in slots.items()}
    if not count:
        return out
    idx = vec_start + 4 * np.arange(count, dtype=np.int64)
    tpos = idx + np.frombuffer(buf, dtype="<u4", count=count, offset=vec_start).astype(np.int64)
    if int(tpos.max()) + 4 > n:
        raise FlatBufferError("a table of the vector lies outside the buffer", vec_start)
    so = _gather(raw, tpos, "<i4")
    vts = tpos - so
    for vt in np.unique(vts).tolist():
        if vt < 0 or vt + 4 > n or vt % 2:
            raise FlatBufferError("vtable offset outside the buffer", vt)
        vt_len = _U16.unpack_from(buf, vt)[0]
        if vt_len < 4 or vt_len % 2 or vt + vt_len > n:
            raise FlatBufferError("bad vtable size", vt)
        sel = np.flatnonzero(vts == vt)
        for slot, dt in slots.items():
            entry = 4 + 2 * slot
            if entry + 2 > vt_len:
                continue
            off = _U16.unpack_from(buf, vt + entry)[0]
            if not off:
                continue
            pos = tpos[sel] + off
            size = np.dtype(dt).itemsize
            if int(pos.max()) + size > n:
                raise FlatBufferError(f"field {slot} outside the buffer", int(pos.max()))
            out[slot][sel] = _gather(raw, pos, dt)
    return out


def _gather(raw, pos, dt: str):
    import numpy as np

    size = np.dtype(dt).itemsize
    return raw[pos[:, None] + np.arange(size)].copy().view(dt).reshape(-1)


_LAYOUTS: dict[tuple[bytes, str], tuple[struct.Struct, tuple[int, ...], int]] = {}


def _layout(vtable: bytes, fmt: str) -> tuple[struct.Struct, tuple[int, ...], int]:
    """One struct covering every wanted field of tables with this vtable, the slot order of its values
    (-1 = absent field, read as 0), and the inline size it needs. Cached: DV repeats a few vtables."""
    key = (vtable, fmt)
    hit = _LAYOUTS.get(key)
    if hit is not None:
        return hit
    offs = struct.unpack(f"<{len(vtable) // 2}H", vtable)[2:]
    present = sorted((offs[slot], slot, code) for slot, code in enumerate(fmt) if slot < len(offs) and offs[slot])
    parts, at, order = ["<"], 0, {}
    for off, slot, code in present:
        if off < at:  # overlapping fields: not a layout any writer produces; read field by field instead
            parts, order = None, None
            break
        parts.append(f"{off - at}x{code}" if off > at else code)
        order[slot] = len(order)
        at = off + struct.calcsize("<" + code)
    if parts is None:
        return None  # type: ignore[return-value]
    layout = (struct.Struct("".join(parts)), tuple(order.get(slot, -1) for slot in range(len(fmt))), at)
    if len(_LAYOUTS) < 256:
        _LAYOUTS[key] = layout
    return layout


def table_scalars(buf, offset_pos: int, fmt: str) -> tuple:
    """Scalar fields of the table that the u32 offset at `offset_pos` points to; slot i has struct code fmt[i].

    Absent fields read as 0. The vtable's layout is compiled once into a single struct (a fast path for the
    small IMU/trigger tables DV writes by the thousand).
    """
    n = len(buf)
    if offset_pos + 4 > n:
        raise FlatBufferError("table offset outside the buffer", offset_pos)
    pos = offset_pos + _U32.unpack_from(buf, offset_pos)[0]
    if pos + 4 > n:
        raise FlatBufferError("table offset outside the buffer", pos)
    vt = pos - _I32.unpack_from(buf, pos)[0]
    if vt < 0 or vt + 4 > n:
        raise FlatBufferError("vtable offset outside the buffer", pos)
    vt_len = _U16.unpack_from(buf, vt)[0]
    if vt_len < 4 or vt_len % 2 or vt + vt_len > n:
        raise FlatBufferError("bad vtable size", vt)
    layout = _layout(bytes(buf[vt:vt + vt_len]), fmt)
    if layout is None:
        raise FlatBufferError("overlapping table fields", vt)
    st, order, inline = layout
    if pos + inline > n:
        raise FlatBufferError("table fields outside the buffer", pos)
    values = st.unpack_from(buf, pos)
    return tuple(values[i] if i >= 0 else 0 for i in order)
