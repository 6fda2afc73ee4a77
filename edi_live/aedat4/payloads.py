"""Decoders for the small AEDAT4 payloads: IMU samples and triggers (vectors of tables).

IMU and trigger packets hold vectors of FlatBuffers *tables* (fields equal to zero are omitted), so each table is
read through its vtable; the values come out in the field order of IMU_DTYPE / TRIGGER_DTYPE and are packed
straight into the arrays' bytes.
"""

from __future__ import annotations

import struct

import numpy as np

from edi_live.aedat4 import schema as S
from edi_live.datatypes import IMU_DTYPE, TRIGGER_DTYPE


_IMU_ROW = struct.Struct("<q10f")  # IMU_DTYPE's memory layout: t, temperature, accel xyz, gyro xyz, mag xyz
_TRIG_ROW = struct.Struct("<qb")  # TRIGGER_DTYPE's memory layout
assert _IMU_ROW.size == IMU_DTYPE.itemsize and _TRIG_ROW.size == TRIGGER_DTYPE.itemsize


def decode_imu(payload: bytes) -> np.ndarray:
    start, count = S.root_table(payload, b"IMUS").vector(0, 4)
    if count > 16:  # many samples: vectorised gather
        cols = S.table_vector_fields(payload, start, count, {0: "<i8", **{s: "<f4" for s in range(1, 11)}})
        rows = zip(*(cols[s].tolist() for s in range(11)))
    else:  # DV writes 1-20 samples per packet: per-table reads are cheaper than numpy set-up
        rows = (S.table_scalars(payload, start + 4 * i, "q" + "f" * 10) for i in range(count))
    # the slots are in IMU_DTYPE's field order, so the packed rows are the array's bytes
    return np.frombuffer(bytearray(b"".join(_IMU_ROW.pack(*v) for v in rows)), dtype=IMU_DTYPE)


def decode_triggers(payload: bytes) -> np.ndarray:
    start, count = S.root_table(payload, b"TRIG").vector(0, 4)
    rows = (S.table_scalars(payload, start + 4 * i, "qb") for i in range(count))
    return np.frombuffer(bytearray(b"".join(_TRIG_ROW.pack(*v) for v in rows)), dtype=TRIGGER_DTYPE)
