"""The inverse of the decoder: events, APS frames, IMU samples and triggers -> the logic-18 16-bit word
stream, for the emulator and the round-trip tests. Pure, stateful across calls (last timestamp, wrap count).

Input times are device µs (>= 0, non-decreasing across calls). Frames are sent as a global-shutter readout:
at exposure start: frame start, ROI, every reset column, exposure start; at exposure end: exposure end,
every signal column, frame end. Pixel v (10-bit) is sent as reset R and signal S with R - S = v
(R = 1023, or 511 raw on a DAVIS240 whose host doubles samples, so only even v are exact there).
"""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import Frame

SPECIAL_RESET = 0x0001
_TRIGGER_TO_SPECIAL = {2: 2, 1: 3, 3: 4, 5: 16, 4: 17}  # AEDAT4 TriggerType -> wire special number


def _ts_words(dt_hi: int) -> list[int]:
    out = []
    while dt_hi > 0:
        k = min(dt_hi, 0xFFF)
        out.append(0x7000 | k)
        dt_hi -= k
    return out


class WordEncoder:
    """Stateful encoder for one emulated camera. Orientation flags as the device registers report them."""

    def __init__(self, width: int, height: int, *, dvs_orientation: int = 0, aps_orientation: int = 0,
                 imu_orientation: int = 0, adc_x2: bool = False, accel_scale: int = 1, gyro_scale: int = 1) -> None:
        self.width, self.height = width, height
        self.dvs_swap = bool(dvs_orientation & 4)
        self.aps_swap, self.aps_flip_x, self.aps_flip_y = (bool(aps_orientation & b) for b in (4, 2, 1))
        self.imu_flip = np.array([-1 if imu_orientation & b else 1 for b in (4, 2, 1)], dtype=np.int64)
        self.adc_x2 = adc_x2
        self.accel_scale, self.gyro_scale = accel_scale, gyro_scale
        self.last_t = 0       # device µs of the last timestamp sent
        self.last_y = -1
        self.started = False  # no timestamp word sent yet

    # ---- time -----------------------------------------------------------------------------------------
    def _time_words(self, t: int) -> list[int]:
        if t < self.last_t:
            raise ValueError(f"encoder input must be time-ordered (got {t} µs after {self.last_t} µs)")
        if self.started and t == self.last_t:
            return []
        words = _ts_words((t >> 15) - (self.last_t >> 15)) + [0x8000 | (t & 0x7FFF)]
        self.last_t, self.started, self.last_y = t, True, -1
        return words

    def timestamp_reset(self) -> np.ndarray:
        """The reset special word; device time restarts at 0 after it."""
        self.last_t, self.started, self.last_y = 0, False, -1
        return np.array([SPECIAL_RESET], dtype=np.uint16)

    # ---- events (vectorised) ---------------------------------------------------------------------------
    def encode_events(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> np.ndarray:
        n = t.shape[0]
        if n == 0:
            return np.zeros(0, np.uint16)
        t = t.astype(np.int64)
        if t[0] < self.last_t or np.any(np.diff(t) < 0):
            raise ValueError("encoder events must be time-ordered and not earlier than the stream")
        row, col = (x, y) if self.dvs_swap else (y, x)  # a swapped device sends x in the row word
        row = row.astype(np.int64)
        prev_t = np.concatenate([[self.last_t], t[:-1]])
        new_ts = t != prev_t
        if not self.started:
            new_ts[0] = True
        prev_row = np.concatenate([[self.last_y], row[:-1]])
        new_y = new_ts | (row != prev_row)
        wraps = np.where(new_ts, (t >> 15) - (prev_t >> 15), 0)
        n_wrap = (wraps + 0xFFE) // 0xFFF
        counts = n_wrap + new_ts + new_y + 1
        end = np.cumsum(counts)
        out = np.empty(int(end[-1]), dtype=np.uint16)
        x_pos = end - 1
        out[x_pos] = (0x2000 | col.astype(np.int64) | (p.astype(np.int64) << 12)).astype(np.uint16)
        yi = np.flatnonzero(new_y)
        out[x_pos[yi] - 1] = (0x1000 | row[yi]).astype(np.uint16)
        ti = np.flatnonzero(new_ts)
        out[x_pos[ti] - 1 - new_y[ti]] = (0x8000 | (t[ti] & 0x7FFF)).astype(np.uint16)
        for i in np.flatnonzero(n_wrap).tolist():
            ws = _ts_words(int(wraps[i]))
            s = int(x_pos[i]) - 2 - len(ws)  # wraps, ts, y, x: a new ts always brings a new Y word
            out[s:s + len(ws)] = ws
        self.last_t, self.last_y, self.started = int(t[-1]), int(row[-1]), True
        return out

    # ---- blocks at one instant -------------------------------------------------------------------------
    def encode_special(self, t: int, number: int) -> np.ndarray:
        return np.array(self._time_words(t) + [number & 0xFFF], dtype=np.uint16)

    def encode_trigger(self, t: int, trigger_type: int) -> np.ndarray:
        if trigger_type not in _TRIGGER_TO_SPECIAL:
            return np.zeros(0, np.uint16)
        return self.encode_special(t, _TRIGGER_TO_SPECIAL[trigger_type])

    def encode_imu(self, t: int, accel_g, gyro_dps, temperature_c: float) -> np.ndarray:
        a_lsb = 16384 >> self.accel_scale
        g_lsb = 131.072 / (1 << self.gyro_scale)
        acc = np.clip(np.rint(np.asarray(accel_g, np.float64) * a_lsb) * self.imu_flip, -32768, 32767)
        gyr = np.clip(np.rint(np.asarray(gyro_dps, np.float64) * g_lsb) * self.imu_flip, -32768, 32767)
        tmp = np.clip(np.rint((temperature_c - 35.0) * 340.0), -32768, 32767)
        vals = [*acc.astype(np.int64).tolist(), int(tmp), *gyr.astype(np.int64).tolist()]
        data = []
        for v in vals:
            v &= 0xFFFF
            data += [0x5000 | (v >> 8), 0x5000 | (v & 0xFF)]
        cfg = 0x5300 | 0xE0 | (self.accel_scale << 2) | self.gyro_scale
        return np.array(self._time_words(t) + [5, cfg] + data + [7], dtype=np.uint16)

    def frame_pixels_10bit(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.dtype == np.uint8:
            return img.astype(np.int64) << 2
        return np.asarray(img, np.int64) >> 6 if img.dtype == np.uint16 else np.clip(img, 0, 1023).astype(np.int64)

    def _readout_matrix(self, image: np.ndarray) -> np.ndarray:
        """Image (h, w) -> A[column count, row count] in the order the device reads it (inverse of decoder)."""
        a = image if self.aps_swap else image.T
        if self.aps_flip_y:
            a = a[:, ::-1]
        if self.aps_flip_x:
            a = a[::-1, :]
        return a

    def _columns(self, a: np.ndarray, start: int) -> np.ndarray:
        ex, ey = a.shape
        out = np.empty((ex, ey + 2), dtype=np.uint16)
        out[:, 0] = start
        out[:, 1:-1] = 0x4000 | a
        out[:, -1] = 13
        return out.reshape(-1)

    def encode_frame_start(self, t: int, frame: Frame) -> np.ndarray:
        h, w = frame.image.shape
        roi = []
        for v in (0, 0, w - 1, h - 1):
            roi += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
        v10 = self._readout_matrix(self.frame_pixels_10bit(frame.image))
        reset = np.full(v10.shape, 511 if self.adc_x2 else 1023, dtype=np.uint16)
        frame_start = self._time_words(t) + [8] + roi
        return np.concatenate([np.array(frame_start, np.uint16), self._columns(reset, 11),
                               np.array([14], np.uint16)])

    def encode_frame_end(self, t: int, frame: Frame) -> np.ndarray:
        v10 = self._readout_matrix(self.frame_pixels_10bit(frame.image))
        if self.adc_x2:
            sig = np.clip((1022 - v10) >> 1, 0, 511)
        else:
            sig = 1023 - v10
        return np.concatenate([np.array(self._time_words(t) + [15], np.uint16),
                               self._columns(sig.astype(np.uint16), 12), np.array([10], np.uint16)])
