"""IMU sample assembly for the DAVIS word decoder: the bytes of one sample in, physical units out.

Owns the sample in progress: which quantities it carries (accelerometer, temperature, gyroscope, from its
configuration byte), the full-scale ranges, and the big-endian 16-bit values collected so far. A sample is
emitted at its end word only if all 14 bytes arrived; axes follow the IMU ORIENTATION_INFO flips.
"""

from __future__ import annotations

import numpy as np

IMU_ACCEL, IMU_GYRO, IMU_TEMP = 0x04, 0x02, 0x01


class ImuSampleAssembler:
    """`orientation`: the ORIENTATION_INFO register (bit 2/1/0 flip X/Y/Z); `imu_type` 2 = MPU-9250 (its
    temperature scale), else MPU-6050. Counts emitted samples into `counters["imu"]`."""

    def __init__(self, orientation: int, imu_type: int, counters: dict[str, int]) -> None:
        self.flip = np.array([-1.0 if orientation & b else 1.0 for b in (4, 2, 1)], dtype=np.float32)
        self.mpu9250 = imu_type == 2
        self.counters = counters
        self.ignore = True
        self._count = 14
        self._type = 0
        self._tmp = 0
        self._raw = np.zeros(7, dtype=np.int16)
        self._accel_scale = 8192.0
        self._gyro_scale = 65.536

    def drop_partial(self) -> None:
        self.ignore = True

    def start(self) -> None:
        """Special 5: a sample starts."""
        self.ignore = False
        self._count = 0
        self._type = 0
        self._raw[:] = 0

    def configure(self, byte: int) -> None:
        """misc8 sub 3: full-scale ranges and which quantities follow."""
        if self.ignore:
            return
        self._accel_scale = 65536.0 / (4 * (1 << ((byte >> 2) & 3)))
        self._gyro_scale = 65536.0 / (500 * (1 << (byte & 3)))
        self._type = (byte >> 5) & 7
        self._count = 0 if self._type & IMU_ACCEL else 6 if self._type & IMU_TEMP else \
            8 if self._type & IMU_GYRO else 14

    def byte(self, byte: int) -> None:
        """misc8 sub 0: the next data byte (high byte first; quantities not carried are skipped)."""
        if self.ignore or self._count >= 14:
            return
        c = self._count
        if c % 2 == 0:
            self._tmp = byte
        else:
            v = (self._tmp << 8) | byte
            self._raw[c // 2] = v - 0x10000 if v >= 0x8000 else v
            if c == 5 and not self._type & IMU_TEMP:
                self._count += 2 if self._type & IMU_GYRO else 8
            elif c == 7 and not self._type & IMU_GYRO:
                self._count += 6
        self._count += 1

    def end(self, t: int) -> tuple | None:
        """Special 7: the finished sample as an IMU_DTYPE row tuple, or None if it is incomplete."""
        if self.ignore:
            return None
        self.ignore = True
        if self._count != 14:
            return None
        raw = self._raw.astype(np.float32)
        temp = raw[3] / 333.87 + 21.0 if self.mpu9250 else raw[3] / 340.0 + 35.0
        accel = raw[0:3] * self.flip / self._accel_scale
        gyro = raw[4:7] * self.flip / self._gyro_scale
        self.counters["imu"] += 1
        return (t, temp, accel, gyro, (0.0, 0.0, 0.0))
