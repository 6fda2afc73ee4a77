"""Pure, incremental DAVIS word decoder: USB bytes in, `Packet`s out (logic 18 word format).

Owns all decoding state across calls: the odd trailing byte, timestamp wrap sum and reset offset, last row,
the APS frame being assembled, the IMU sample being assembled. DVS events and timestamps go through the hot
kernel in `_kernel.py` (numba, numpy fallback); APS samples are handled column-wise with numpy; the few
remaining words (specials, ROI, IMU bytes) run through a small Python state machine.

Time: device µs + `time_offset_us`. A timestamp reset mid-stream shifts the offset so output time never goes
backwards, drops the frame and IMU sample in progress, adds a TIMESTAMP_RESET trigger and marks the packet
`gap`. After `mark_gap()` (raw data lost upstream) the wrap count is re-anchored from host arrival times.
No I/O, no threads, no clocks.
"""

from __future__ import annotations

import numpy as np

from drivers.davis import _kernel
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, Frame, Packet, empty_events

APS_ADC_MAX = 1023
WHITE_RESET_MIN = 384
# wire special-event numbers (code 0) -> AEDAT4 TriggerType
TRIGGER_OF_SPECIAL = {2: 2, 3: 1, 4: 3, 16: 5, 17: 4}
TRIGGER_TIMESTAMP_RESET = 0
IMU_ACCEL, IMU_GYRO, IMU_TEMP = 0x04, 0x02, 0x01


class DavisDecoder:
    """Incremental decoder for one camera's word stream.

    dvs_columns/dvs_rows and aps_columns/aps_rows are the SIZE registers (before any swap); orientations are
    the ORIENTATION_INFO registers (DVS bit 2 swap; APS bit 2 swap, bit 1 flip X, bit 0 flip Y; IMU bit 2/1/0
    flip X/Y/Z). `frame_bits` 8 gives uint8 frames (ADC >> 2, like DV recordings), 16 gives uint16 (ADC << 6).
    """

    def __init__(self, dvs_columns: int, dvs_rows: int, aps_columns: int | None = None,
                 aps_rows: int | None = None, *, dvs_orientation: int = 0, aps_orientation: int = 0,
                 imu_orientation: int = 0, imu_type: int = 1, adc_x2: bool = False, time_offset_us: int = 0,
                 frame_bits: int = 8, use_numba: bool | None = None) -> None:
        if frame_bits not in (8, 16):
            raise ValueError(f"frame_bits must be 8 or 16 (got {frame_bits})")
        self.dvs_cols, self.dvs_rows = int(dvs_columns), int(dvs_rows)
        self.dvs_swap = bool(dvs_orientation & 4)
        self.aps_cols = int(aps_columns if aps_columns is not None else dvs_columns)
        self.aps_rows = int(aps_rows if aps_rows is not None else dvs_rows)
        self.aps_swap, self.aps_flip_x, self.aps_flip_y = (bool(aps_orientation & b) for b in (4, 2, 1))
        self.imu_flip = np.array([-1.0 if imu_orientation & b else 1.0 for b in (4, 2, 1)], dtype=np.float32)
        self.imu_9250 = imu_type == 2
        self.adc_x2 = bool(adc_x2)
        self.frame_bits = frame_bits
        self.use_numba = use_numba
        self._state = _kernel.new_state(time_offset_us)
        self._carry = b""
        self._reanchor = False
        self._last_arrival_ns = 0
        self._host_minus_dev_us: int | None = None  # smallest recent (arrival - device time): latency floor
        self._seq = 0
        self._wm = -(2**62)  # highest watermark promised so far; later events are clamped to it
        self.counters = {"words": 0, "events": 0, "frames": 0, "frames_dropped": 0, "imu": 0,
                         "timestamp_resets": 0, "bad_words": 0, "backwards_events": 0, "gaps": 0, "skipped_words": 0}
        # APS state
        self._aps_ignore = True  # until the first frame start (stale data at startup)
        self._roi = [0, 0, self.aps_width - 1, self.aps_height - 1]
        self._roi_tmp = 0
        self._roi_update = 0
        self._frame: dict | None = None
        self._col_type = -1
        self._col_parts: list[np.ndarray] = []
        # IMU state
        self._imu_ignore = True
        self._imu_count = 14
        self._imu_type = 0
        self._imu_tmp = 0
        self._imu_raw = np.zeros(7, dtype=np.int16)
        self._accel_scale = 8192.0
        self._gyro_scale = 65.536

    # ---- public -------------------------------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.dvs_rows if self.dvs_swap else self.dvs_cols

    @property
    def height(self) -> int:
        return self.dvs_cols if self.dvs_swap else self.dvs_rows

    @property
    def aps_width(self) -> int:
        return self.aps_rows if self.aps_swap else self.aps_cols

    @property
    def aps_height(self) -> int:
        return self.aps_cols if self.aps_swap else self.aps_rows

    @property
    def watermark_us(self) -> int:
        """No later packet holds an event earlier than this (the current output time)."""
        return self._wm

    def anchor(self, arrival_ns: int) -> None:
        """Host time (monotonic ns) at which the device's current time was reached, e.g. when streaming
        started at device time 0; lets a gap before the first chunk still be re-anchored."""
        self._last_arrival_ns = int(arrival_ns)
        self._host_minus_dev_us = int(arrival_ns) // 1000 - int(self._state[_kernel.S_CURRENT])

    def mark_gap(self) -> None:
        """Raw bytes were lost before the next chunk: drop partial frame/IMU/row state, re-anchor the wrap
        count on the next chunk from host arrival times, and flag the next packet as `gap`."""
        self._carry = b""
        self._state[_kernel.S_LAST_Y] = -1
        self._drop_partial()
        self._reanchor = True
        self.counters["gaps"] += 1

    def decode(self, data: bytes | bytearray | memoryview | np.ndarray, arrival_ns: int = 0) -> Packet:
        """Decode one chunk of the USB byte stream (any length; an odd byte is carried to the next call)."""
        raw = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
        if self._carry:
            raw = np.concatenate([np.frombuffer(self._carry, dtype=np.uint8), raw])
            self._carry = b""
        if raw.size & 1:
            self._carry = raw[-1:].tobytes()
            raw = raw[:-1]
        words = raw.view("<u2")
        return self.decode_words(words, arrival_ns)

    def decode_words(self, words: np.ndarray, arrival_ns: int = 0) -> Packet:
        gap = False
        if self._reanchor:
            words = self._apply_reanchor(words, arrival_ns)
            gap = True
        self.counters["words"] += int(words.size)
        bad_before = int(self._state[_kernel.S_BAD])
        self._state[_kernel.S_LAST_OUT] = max(int(self._state[_kernel.S_LAST_OUT]), self._wm)
        ev2, ctrl_idx, ctrl_t = _kernel.scan(words, self._state, self.dvs_cols, self.dvs_rows, self.dvs_swap,
                                             self.use_numba)
        self.counters["bad_words"] += int(self._state[_kernel.S_BAD]) - bad_before
        self.counters["backwards_events"] = int(self._state[_kernel.S_BACKWARDS])
        self._wm = max(self._wm, int(self._state[_kernel.S_CURRENT] + self._state[_kernel.S_OFFSET]))
        if ev2.shape[0] < words.shape[0] // 2:
            ev2 = ev2.copy()  # do not pin a mostly empty buffer
        events = ev2.view(EVENT_DTYPE).reshape(-1) if ev2.size else empty_events()
        self.counters["events"] += int(events.shape[0])
        out = _Out()
        if ctrl_idx.size:
            gap |= self._control(words[ctrl_idx], ctrl_t, out)
        if arrival_ns:
            self._track_latency(arrival_ns)
        imu = np.array(out.imu, dtype=IMU_DTYPE) if out.imu else np.zeros(0, IMU_DTYPE)
        trig = np.array(out.triggers, dtype=TRIGGER_DTYPE) if out.triggers else np.zeros(0, TRIGGER_DTYPE)
        return Packet(events=events, frames=out.frames, imu=imu, triggers=trig, watermark_us=self.watermark_us,
                      arrival_ns=arrival_ns, gap=gap)

    # ---- gap re-anchoring ----------------------------------------------------------------------------
    def _track_latency(self, arrival_ns: int) -> None:
        """Keep the smallest host-minus-device offset seen (data never arrives before its timestamp). It may
        rise by 1 ms per s so that a device clock running slower than the host (ppm drift) is followed."""
        off = arrival_ns // 1000 - int(self._state[_kernel.S_CURRENT])
        if self._host_minus_dev_us is None:
            self._host_minus_dev_us = off
        else:
            rise = max(0, arrival_ns - self._last_arrival_ns) // 1_000_000
            self._host_minus_dev_us = min(off, self._host_minus_dev_us + rise)
        self._last_arrival_ns = arrival_ns

    def _apply_reanchor(self, words: np.ndarray, arrival_ns: int) -> np.ndarray:
        """Drop words before the first timestamp word, then pick the wrap count that puts this chunk's last
        timestamp just before the host arrival time says it was sent."""
        ts_pos = np.flatnonzero(words >= 0x8000)
        if ts_pos.size == 0:
            self.counters["skipped_words"] += int(words.size)
            return words[:0]  # still no anchor; keep waiting
        first = int(ts_pos[0])
        self.counters["skipped_words"] += first
        words = words[first:]
        self._reanchor = False
        st = self._state
        last_dev = int(st[_kernel.S_CURRENT])
        probe = _kernel.new_state(0)
        probe[_kernel.S_LAST_Y] = 0
        _kernel.scan(words, probe, self.dvs_cols, self.dvs_rows, False, self.use_numba)
        rel_end = int(probe[_kernel.S_CURRENT])
        first_low = int(words[0]) & 0x7FFF
        if arrival_ns and self._host_minus_dev_us is not None:
            # data reaches the host after its timestamp (USB latency, a reader running behind), so arrival time
            # minus the smallest latency seen is an upper bound of the chunk's end: take the latest wrap that
            # does not put the end after it (2 ms slack for clock granularity). Exact while this chunk's latency
            # exceeds the smallest one by less than one wrap period (32.8 ms) minus the slack.
            target_end = arrival_ns // 1000 - self._host_minus_dev_us + 2000
            base = ((target_end - rel_end) // _kernel.WRAP_STEP) * _kernel.WRAP_STEP
        else:
            base = (last_dev >> 15) << 15
        min_base = (last_dev >> 15) << 15
        base = max(base, min_base)
        if base + first_low < last_dev:
            base += _kernel.WRAP_STEP
        st[_kernel.S_WRAP] = base
        return words

    # ---- control words: specials, APS, IMU ------------------------------------------------------------
    def _drop_partial(self) -> None:
        if self._frame is not None:
            self.counters["frames_dropped"] += 1
        self._frame = None
        self._col_type = -1
        self._col_parts = []
        self._aps_ignore = True
        self._imu_ignore = True

    def _control(self, cw: np.ndarray, ct: np.ndarray, out: "_Out") -> bool:
        gap = False
        ns = np.flatnonzero((cw >> 12) != 4)  # every control word that is not an APS sample
        runs = self._column_runs(cw, ns)
        prev = 0
        k, n = 0, ns.shape[0]
        ns_list = ns.tolist()
        while k < n:
            j = ns_list[k]
            if k in runs and self._frame is not None and not self._aps_ignore and self._col_type < 0:
                k_end, length = runs[k]  # k .. k_end: complete columns of one type and one length
                self._column_block(cw, ns[k:k_end + 1:2], int(cw[j]) - 11, length)
                prev = ns_list[k_end + 1] + 1
                k = k_end + 2
                continue
            if j > prev:
                self._samples(cw[prev:j])
            prev = j + 1
            w = int(cw[j])
            code, data, t = w >> 12, w & 0xFFF, int(ct[j])
            if code == 0:
                gap |= self._special(data, t, out)
            elif code == 5:
                self._misc8((data >> 8) & 0xF, data & 0xFF, t, out)
            # code 6 (misc10: exposure in ADC cycles, for auto-exposure) is not needed
            k += 1
        if prev < cw.shape[0]:
            self._samples(cw[prev:])
        return gap

    @staticmethod
    def _column_runs(cw: np.ndarray, ns: np.ndarray) -> dict[int, tuple[int, int]]:
        """Runs of complete columns (start 11/12, samples, end 13) of one type and one length, keyed by the
        index in `ns` of the first column start: {k: (index of the last column start, samples per column)}.
        They are decoded as one 2-D block instead of word by word."""
        if ns.shape[0] < 4:
            return {}
        codes = cw[ns].astype(np.int64)
        starts = np.flatnonzero(((codes[:-1] == 11) | (codes[:-1] == 12)) & (codes[1:] == 13))
        if starts.shape[0] < 2:
            return {}
        length = ns[starts + 1] - ns[starts] - 1
        brk = (np.diff(starts) != 2) | (np.diff(codes[starts]) != 0) | (np.diff(length) != 0)
        first = np.concatenate([[0], np.flatnonzero(brk) + 1])
        last = np.concatenate([first[1:] - 1, [starts.shape[0] - 1]])
        return {int(starts[f]): (int(starts[l]), int(length[f])) for f, l in zip(first.tolist(), last.tolist())
                if l > f}

    def _column_block(self, cw: np.ndarray, col_starts: np.ndarray, r: int, length: int) -> None:
        f = self._frame
        ex, ey, _, _ = self._expected()
        take = min(col_starts.shape[0], ex - f["count"][r])
        if take <= 0:
            return
        idx = col_starts[:take, None] + 1 + np.arange(min(length, ey))
        f["cols"][r].append(cw[idx] & 0x3FF)
        f["count"][r] += take

    def _samples(self, s: np.ndarray) -> None:
        if self._aps_ignore or self._frame is None or self._col_type < 0:
            return
        self._col_parts.append(s & 0x3FF)

    def _special(self, data: int, t: int, out: "_Out") -> bool:
        if data == 1:  # timestamp reset
            self.counters["timestamp_resets"] += 1
            had_data = self.counters["events"] > 0 or self._seq > 0
            self._drop_partial()
            if had_data:
                out.triggers.append((t, TRIGGER_TIMESTAMP_RESET))
            return had_data
        if data in TRIGGER_OF_SPECIAL:
            out.triggers.append((t, TRIGGER_OF_SPECIAL[data]))
        elif data == 5:
            self._imu_ignore = False
            self._imu_count = 0
            self._imu_type = 0
            self._imu_raw[:] = 0
        elif data == 7:
            self._imu_end(t, out)
        elif data in (8, 9):
            self._frame_start(t)
        elif data == 10:
            self._frame_end(t, out)
        elif data in (11, 12):
            if not self._aps_ignore:
                self._col_type = data - 11
                self._col_parts = []
        elif data == 13:
            self._column_end()
        elif data == 14 and self._frame is not None:
            self._frame["exp_start"] = t
        elif data == 15 and self._frame is not None:
            self._frame["exp_end"] = t
        elif data in (0, 6) or data > 17:
            self.counters["bad_words"] += 1
        return False

    def _frame_start(self, t: int) -> None:
        if self._frame is not None:
            self.counters["frames_dropped"] += 1
        self._aps_ignore = False
        self._roi_update = 0
        self._frame = {"start": t, "exp_start": None, "exp_end": None, "count": [0, 0], "cols": [[], []],
                       "roi": None}
        self._col_type = -1

    def _expected(self) -> tuple[int, int, int, int]:
        x0, y0, x1, y1 = self._roi
        w, h = x1 + 1 - x0, y1 + 1 - y0
        if w <= 0 or h <= 0 or x1 >= self.aps_width or y1 >= self.aps_height:
            w, h = self.aps_width, self.aps_height
        return (h, w, w, h) if self.aps_swap else (w, h, w, h)

    def _column_end(self) -> None:
        f = self._frame
        if self._aps_ignore or f is None or self._col_type < 0:
            return
        ex, ey, _, _ = self._expected()
        r = self._col_type
        col = np.concatenate(self._col_parts) if self._col_parts else np.zeros(0, np.uint16)
        self._col_parts = []
        self._col_type = -1
        if f["count"][r] < ex:
            f["cols"][r].append(col[None, :ey])
            f["count"][r] += 1

    def _frame_end(self, t: int, out: "_Out") -> None:
        f = self._frame
        if self._aps_ignore or f is None:
            return
        self._frame = None
        ex, ey, w, h = self._expected()
        if f["count"][0] != ex or f["count"][1] != ex:
            self.counters["frames_dropped"] += 1
            return
        reset, signal = (self._assemble(f["cols"][r], ex, ey) for r in (0, 1))
        if self.adc_x2:
            reset <<= 1
            signal <<= 1
        pix = np.clip(reset - signal, 0, APS_ADC_MAX)
        pix[(reset < WHITE_RESET_MIN) | (signal == 0)] = APS_ADC_MAX
        if self.aps_flip_x:
            pix = pix[::-1, :]
        if self.aps_flip_y:
            pix = pix[:, ::-1]
        img = pix if self.aps_swap else pix.T
        img = (img >> 2).astype(np.uint8) if self.frame_bits == 8 else (img << 6).astype(np.uint16)
        es = f["exp_start"] if f["exp_start"] is not None else f["start"]
        ee = f["exp_end"] if f["exp_end"] is not None else t
        ee = max(ee, es)
        out.frames.append(Frame(np.ascontiguousarray(img), int(es), int(ee), int(f["start"]), int(t), self._seq))
        self._seq += 1
        self.counters["frames"] += 1

    @staticmethod
    def _assemble(cols: list[np.ndarray], ex: int, ey: int) -> np.ndarray:
        a = np.zeros((ex, ey), dtype=np.int32)  # missing samples read as 0 -> white, like an unwritten pixel
        i = 0
        for block in cols:  # 2-D blocks of whole columns
            a[i:i + block.shape[0], : block.shape[1]] = block
            i += block.shape[0]
        return a

    def _misc8(self, sub: int, byte: int, t: int, out: "_Out") -> None:
        if sub == 0:
            self._imu_byte(byte)
        elif sub == 1:
            self._roi_tmp = byte << 8
        elif sub == 2:
            self._roi[self._roi_update & 3] = self._roi_tmp | byte
            self._roi_update += 1
        elif sub == 3 and not self._imu_ignore:
            self._accel_scale = 65536.0 / (4 * (1 << ((byte >> 2) & 3)))
            self._gyro_scale = 65536.0 / (500 * (1 << (byte & 3)))
            self._imu_type = (byte >> 5) & 7
            self._imu_count = 0 if self._imu_type & IMU_ACCEL else 6 if self._imu_type & IMU_TEMP else \
                8 if self._imu_type & IMU_GYRO else 14
        else:
            self.counters["bad_words"] += int(sub > 3)

    def _imu_byte(self, byte: int) -> None:
        if self._imu_ignore or self._imu_count >= 14:
            return
        c = self._imu_count
        if c % 2 == 0:
            self._imu_tmp = byte
        else:
            v = (self._imu_tmp << 8) | byte
            self._imu_raw[c // 2] = v - 0x10000 if v >= 0x8000 else v
            if c == 5 and not self._imu_type & IMU_TEMP:
                self._imu_count += 2 if self._imu_type & IMU_GYRO else 8
            elif c == 7 and not self._imu_type & IMU_GYRO:
                self._imu_count += 6
        self._imu_count += 1

    def _imu_end(self, t: int, out: "_Out") -> None:
        if self._imu_ignore:
            return
        self._imu_ignore = True
        if self._imu_count != 14:
            return
        raw = self._imu_raw.astype(np.float32)
        temp = raw[3] / 333.87 + 21.0 if self.imu_9250 else raw[3] / 340.0 + 35.0
        accel = raw[0:3] * self.imu_flip / self._accel_scale
        gyro = raw[4:7] * self.imu_flip / self._gyro_scale
        out.imu.append((t, temp, accel, gyro, (0.0, 0.0, 0.0)))
        self.counters["imu"] += 1


class _Out:
    __slots__ = ("frames", "imu", "triggers")

    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self.imu: list = []
        self.triggers: list = []
