"""Decoding of the two large AEDAT4 payloads: EVTS (a zero-copy view in EVENT_DTYPE, checked by `_check`) and
FRME (the image, placed on the sensor for an ROI frame, with its exposure window from SOE/EOE in both DV layouts).

Payloads are decompressed bytes of one packet. A defect raises `RecordingError` without a file position (the
reader adds the file and the packet's byte offset) or `schema.FlatBufferError` from the general vtable walk.
"""

from __future__ import annotations

import struct

import numpy as np

from edi_live.aedat4 import schema as S
from edi_live.aedat4._check import check_events, parse_check_evts
from edi_live.aedat4.header import StreamInfo
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.errors import RecordingError

_I8, _I16, _I32, _I64 = (struct.Struct(f) for f in ("<b", "<h", "<i", "<q"))
_U32 = struct.Struct("<I")
_EVTS_HEAD = struct.Struct("<II4s")
_VT3 = struct.Struct("<HHH")

_T_MIN = -(2**62)  # "no floor" (a smaller Python int makes numba dispatch 20x slower)
_WHY = {1: "goes back in time", 2: "lies outside the {w}x{h} sensor", 3: "has a polarity byte other than 0/1",
        4: "has a timestamp beyond ±2**62 µs (146,000 years)"}
NO_EVENTS = np.zeros(0, dtype=EVENT_DTYPE)
NO_EVENTS.flags.writeable = False


def _bad_event(stream: StreamInfo, first: int, count: int, why: int) -> RecordingError:
    return RecordingError(f"corrupt event packet of stream {stream.id}: event {first} of {count} "
                          f"{_WHY[why].format(w=stream.width, h=stream.height)}")


def decode_events(payload: bytes, stream: StreamInfo, validate: bool = True) -> np.ndarray:
    """The events of an EVTS payload as a read-only EVENT_DTYPE view of it; with `validate`, each packet is
    checked to be sorted by time, on the sensor and with polarity 0/1."""
    if validate:  # the plain layout: parse and check in one compiled call
        start, count, first, why = parse_check_evts(np.frombuffer(payload, np.uint8), stream.width, stream.height)
        if start >= 0:
            if why:
                raise _bad_event(stream, first, count, why)
            return np.frombuffer(payload, dtype=EVENT_DTYPE, count=count, offset=start) if count else NO_EVENTS
    start, count = _events_vector(payload)
    if not count:
        return NO_EVENTS
    if validate:
        first, why = check_events(np.frombuffer(payload, np.uint8, count * 16, start), stream.width, stream.height,
                                  _T_MIN)
        if why:
            raise _bad_event(stream, first, count, why)
    return np.frombuffer(payload, dtype=EVENT_DTYPE, count=count, offset=start)


def _events_vector(payload: bytes) -> tuple[int, int]:
    """(start, count) of the event records: the vtable walk of schema.Table inlined for the common layout (this
    runs once per event packet without validation), else the general, fully checked walk (FlatBufferError)."""
    n = len(payload)
    if n >= 16:
        size, root, ident = _EVTS_HEAD.unpack_from(payload, 0)
        table = root + 4
        if ident == b"EVTS" and size + 4 <= n and table + 4 <= n:
            vt = table - _I32.unpack_from(payload, table)[0]
            if 0 <= vt <= n - 6:
                vt_len, _, off = _VT3.unpack_from(payload, vt)
                field = table + off
                if vt_len >= 6 and off and field + 4 <= n:
                    v = field + _U32.unpack_from(payload, field)[0]
                    if v + 4 <= n:
                        count = _U32.unpack_from(payload, v)[0]
                        if v + 4 + 16 * count <= n:
                            return v + 4, count
    return S.root_table(payload, b"EVTS").vector(0, S.EVENT_RECORD_BYTES)


def decode_frame(payload: bytes, stream: StreamInfo, seq: int) -> Frame:
    """An FRME payload as a `Frame`, an ROI placed on the full sensor: gray (a raw Bayer mosaic tagged with its
    pattern when the stream's metadata names one), or BGR (h, w, 3) for BGR and BGRA frames (alpha dropped)."""
    tb = S.root_table(payload, b"FRME")
    ts = tb.scalar(S.FR_TIMESTAMP, _I64)
    soe, eoe = tb.scalar(S.FR_SOE, _I64), tb.scalar(S.FR_EOE, _I64)
    sof, eof = tb.scalar(S.FR_SOF, _I64), tb.scalar(S.FR_EOF, _I64)
    exposure = tb.scalar(S.FR_EXPOSURE, _I64, None)
    fmt = tb.scalar(S.FR_FORMAT, _I8)
    w, h = tb.scalar(S.FR_SIZE_X, _I16), tb.scalar(S.FR_SIZE_Y, _I16)
    px, py = tb.scalar(S.FR_POS_X, _I16), tb.scalar(S.FR_POS_Y, _I16)
    if fmt not in S.FRAME_FORMAT_CHANNELS:
        raise RecordingError(f"frame pixel format {fmt} is not supported (8/16-bit gray, BGR or BGRA)")
    channels, depth = S.FRAME_FORMAT_CHANNELS[fmt]
    if w <= 0 or h <= 0 or px < 0 or py < 0:
        raise RecordingError(f"frame with invalid size {w}x{h} at ({px}, {py})")
    start, count = tb.vector(S.FR_PIXELS, 1)
    if count != w * h * channels * depth:
        raise RecordingError(f"frame holds {count} pixel bytes, {w}x{h}x{channels}x{depth} expected")
    dtype = np.uint8 if depth == 1 else np.dtype("<u2")
    img = np.frombuffer(payload, dtype=dtype, count=w * h * channels, offset=start)
    img = img.reshape(h, w) if channels == 1 else np.ascontiguousarray(img.reshape(h, w, channels)[..., :3])
    if stream.width and stream.height and (w, h) != (stream.width, stream.height):
        if px + w > stream.width or py + h > stream.height:  # the reconstructor, set up for the sensor, refuses it
            raise RecordingError(f"frame of {w}x{h} at ({px}, {py}) does not fit the {stream.width}x{stream.height} "
                                 f"sensor the header declares")
        full = np.zeros((stream.height, stream.width) + img.shape[2:], dtype=img.dtype)  # an ROI frame: on the sensor
        full[py:py + h, px:px + w] = img
        img = full
    if soe or eoe:
        lo, hi = soe, eoe if eoe else soe + (exposure or 0)
    else:  # no exposure timestamps: newer layouts give timestamp = start plus an exposure duration
        lo, hi = ts, ts + (exposure or 0)
    if hi < lo or (exposure is not None and exposure < 0):
        raise RecordingError(f"frame with a negative exposure (start {lo} µs, end {hi} µs)")
    return Frame(image=img, exposure_start_us=lo, exposure_end_us=hi, start_us=sof or None, end_us=eof or None,
                 seq=seq, color_filter=stream.color_filter if channels == 1 else None)
