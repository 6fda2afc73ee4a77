"""AEDAT 4.0 codec: streaming reader and writer (the only users of lz4 and zstandard).

`Aedat4Reader(path)` yields `(StreamInfo, data)` per packet in file order; `Aedat4Writer(path, width, height, ...)`
writes events, frames, IMU and triggers with a FileDataTable. `drivers.replay.merged_packets` turns a file into
time-ordered `Packet`s.
"""

from edi_live.aedat4.reader import DATA_TABLE_DTYPE, Aedat4Reader, StreamInfo
from edi_live.aedat4.writer import Aedat4Writer

__all__ = ["Aedat4Reader", "Aedat4Writer", "StreamInfo", "DATA_TABLE_DTYPE"]
