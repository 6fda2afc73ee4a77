"""The FileDataTable at the end of an AEDAT4 file: one entry per packet (offset, stream, size, element count,
time range). edi-live never needs it to read a file, but a damaged table is damage like any other.
"""

from __future__ import annotations

import numpy as np

from edi_live.aedat4 import schema as S

DATA_TABLE_DTYPE = np.dtype([("byte_offset", "<i8"), ("stream_id", "<i4"), ("size", "<i4"),
                             ("num_elements", "<i8"), ("t_start", "<i8"), ("t_end", "<i8")])
"""One FileDataTable entry: `byte_offset` addresses the packet body (its header is 8 bytes before)."""


def parse_data_table(payload: bytes) -> np.ndarray:
    """The decompressed table as a DATA_TABLE_DTYPE array (missing fields are 0). Raises FlatBufferError, or
    whatever else a damaged table provokes (the reader turns both into a RecordingError)."""
    start, count = S.root_table(payload, b"FTAB").vector(0, 4)
    cols = S.table_vector_fields(payload, start, count, {0: "<i8", 1: "<i8", 2: "<i8", 3: "<i8", 4: "<i8"})
    out = np.zeros(count, dtype=DATA_TABLE_DTYPE)
    info = cols[1].astype("<i8")  # PacketInfo struct {i32 stream id, i32 size}, little-endian
    out["byte_offset"], out["num_elements"], out["t_start"], out["t_end"] = cols[0], cols[2], cols[3], cols[4]
    out["stream_id"], out["size"] = (info & 0xFFFFFFFF).astype("<u4").view("<i4"), (info >> 32)
    return out
