"""AEDAT4 packet compression: one LZ4 or Zstd frame per packet body (and for the FileDataTable).

Owns the codecs for both directions. Reading: DV's LZ4 frames are decoded block by block (see lz4_decompress);
Zstd frames are streamed with an output cap, since a frame need not declare its size. Writing: LZ4 frames without
a content size (as dv-processing writes them) or Zstd frames with one. The only users of lz4 and zstandard.
"""

from __future__ import annotations

import struct
from typing import Callable

import lz4.block
import lz4.frame
import zstandard

MAX_PACKET_BYTES = 1 << 30  # decompressed; a larger packet is treated as corrupt (bounded memory)
_U32 = struct.Struct("<I")
_LZ4_HEAD = struct.Struct("<IBB")  # frame magic, FLG, BD


def lz4_decompress(body) -> bytes:
    """Decompress one LZ4 frame.

    DV's frames (FLG 0x40: linked 64 KB blocks, no checksums, no content size) are decoded block by block with
    lz4.block, each linked block getting the previous 64 KB of output as its dictionary. That is 2-5x faster than
    lz4.frame.decompress, which grows its output buffer by reallocation when the content size is unknown
    (measured in tools/bench_aedat4.py). Frames with checksums or anything unusual go to lz4.frame, which also
    verifies the checksums.
    """
    n = len(body)
    if n < 11:
        return lz4.frame.decompress(body)
    magic, flg, bd = _LZ4_HEAD.unpack_from(body, 0)
    if magic != 0x184D2204 or flg & 0xD5 != 0x40:  # need version 01; no block/content checksum, no dict id
        return lz4.frame.decompress(body)
    max_block = 1 << (8 + 2 * ((bd >> 4) & 7))
    if not flg & 0x08 and n >= 15:  # one block then the end mark: most DV packets (<= 64 KB raw)
        bs = _U32.unpack_from(body, 7)[0]
        size = bs & 0x7FFFFFFF
        if 15 + size == n and size <= max_block and _U32.unpack_from(body, 11 + size)[0] == 0:
            if bs & 0x80000000:
                return bytes(body[11:11 + size])
            return lz4.block.decompress(body[11:11 + size], uncompressed_size=max_block)
    p = 15 if flg & 0x08 else 7
    independent = flg & 0x20
    parts: list[bytes] = []
    window = b""
    decompress = lz4.block.decompress
    while True:
        if p + 4 > n:
            return lz4.frame.decompress(body)  # malformed: let lz4.frame produce the error
        bs = _U32.unpack_from(body, p)[0]
        p += 4
        if bs == 0:
            break
        raw, bs = bs & 0x80000000, bs & 0x7FFFFFFF
        if p + bs > n or bs > max_block:
            return lz4.frame.decompress(body)
        if raw:
            out = bytes(body[p:p + bs])
        elif independent or not parts:
            out = decompress(body[p:p + bs], uncompressed_size=max_block)
        else:
            out = decompress(body[p:p + bs], uncompressed_size=max_block, dict=window)
        parts.append(out)
        if not independent:  # the last 64 KB of output is the next block's dictionary
            window = out if len(out) >= 65536 else (window + out)[-65536:]
        p += bs
    if p != n:
        return lz4.frame.decompress(body)
    return parts[0] if len(parts) == 1 else b"".join(parts)


def decompressor(name: str) -> Callable[[bytes], bytes]:
    """bytes-like packet body -> new bytes, for compression `name` ("none", "lz4", "lz4_high", "zstd", ...)."""
    if name == "none":
        return bytes  # a copy: the reader's read buffer is reused
    if name.startswith("lz4"):
        return lz4_decompress
    dctx = zstandard.ZstdDecompressor()

    def unzstd(body) -> bytes:
        with dctx.stream_reader(body) as reader:
            out = reader.read(MAX_PACKET_BYTES + 1)
        if len(out) > MAX_PACKET_BYTES:
            raise ValueError("decompressed packet larger than 1 GiB")
        return out

    return unzstd


def compressor(name: str) -> Callable[[bytes], bytes]:
    """Packet payload -> one compressed frame, for compression `name`."""
    if name == "none":
        return bytes
    if name in ("lz4", "lz4_high"):
        level = 9 if name == "lz4_high" else 0
        return lambda data: lz4.frame.compress(data, compression_level=level, store_size=False)
    cctx = zstandard.ZstdCompressor(level=19 if name == "zstd_high" else 3, write_content_size=True)
    return cctx.compress
