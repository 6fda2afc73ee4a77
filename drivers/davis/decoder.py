"""Pure, incremental DAVIS word decoder: USB bytes in, `Packet`s out (logic 18 word format).

Owns the decoding state across calls: the odd trailing byte, timestamp wrap sum and reset offset, last row, the
watermark, gap re-anchoring and the counters, and the dispatch of control words. DVS events and timestamps go
through the numba kernel in `_kernel.py`; the few remaining words (specials, ROI, IMU bytes) run through a small
Python state machine that hands them to the APS frame (`aps.ApsFrameAssembler`, samples handled column-wise with
numpy) and the IMU sample (`imu.ImuSampleAssembler`) being assembled.

Time: device µs + `time_offset_us`. A timestamp reset mid-stream shifts the offset so output time never goes
backwards, drops the frame and IMU sample in progress, adds a TIMESTAMP_RESET trigger and marks the packet
`gap`. After `mark_gap()` (raw data lost upstream) the wrap count is re-anchored from host arrival times.
No I/O, no threads, no clocks.
"""

from __future__ import annotations

import numpy as np

from drivers.davis import _kernel
from drivers.davis.aps import ApsFrameAssembler, column_runs
from drivers.davis.imu import ImuSampleAssembler
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, ColorFilter, Frame, Packet, empty_events

# wire special-event numbers (code 0) -> AEDAT4 TriggerType
TRIGGER_OF_SPECIAL = {2: 2, 3: 1, 4: 3, 16: 5, 17: 4}
TRIGGER_TIMESTAMP_RESET = 0


class DavisDecoder:
    """Incremental decoder for one camera's word stream.

    dvs_columns/dvs_rows and aps_columns/aps_rows are the SIZE registers (before any swap); orientations are
    the ORIENTATION_INFO registers (DVS bit 2 swap; APS bit 2 swap, bit 1 flip X, bit 0 flip Y; IMU bit 2/1/0
    flip X/Y/Z). `frame_bits` 8 gives uint8 frames (ADC >> 2, like DV recordings), 16 gives uint16 (ADC << 6).
    `color_filter`: a colour sensor's Bayer pattern (the APS colour-filter register); frames carry it, raw.
    """

    def __init__(self, dvs_columns: int, dvs_rows: int, aps_columns: int | None = None,
                 aps_rows: int | None = None, *, dvs_orientation: int = 0, aps_orientation: int = 0,
                 imu_orientation: int = 0, imu_type: int = 1, adc_x2: bool = False, time_offset_us: int = 0,
                 frame_bits: int = 8, color_filter: ColorFilter | None = None) -> None:
        if frame_bits not in (8, 16):
            raise ValueError(f"frame_bits must be 8 or 16 (got {frame_bits})")
        self.dvs_cols, self.dvs_rows = int(dvs_columns), int(dvs_rows)
        self.dvs_swap = bool(dvs_orientation & 4)
        self._state = _kernel.new_state(time_offset_us)
        self._carry = b""
        self._reanchor = False
        self._last_arrival_ns = 0
        self._host_minus_dev_us: int | None = None  # smallest recent (arrival - device time): latency floor
        self._wm = -(2**62)  # highest watermark promised so far; later events are clamped to it
        self.counters = {"words": 0, "events": 0, "frames": 0, "frames_dropped": 0, "imu": 0,
                         "timestamp_resets": 0, "bad_words": 0, "backwards_events": 0, "gaps": 0, "skipped_words": 0}
        self._aps = ApsFrameAssembler(aps_columns if aps_columns is not None else dvs_columns,
                                      aps_rows if aps_rows is not None else dvs_rows,
                                      swap=bool(aps_orientation & 4), flip_x=bool(aps_orientation & 2),
                                      flip_y=bool(aps_orientation & 1), adc_x2=bool(adc_x2), frame_bits=frame_bits,
                                      counters=self.counters, color_filter=color_filter)
        self._imu = ImuSampleAssembler(imu_orientation, imu_type, self.counters)

    # ---- public -------------------------------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.dvs_rows if self.dvs_swap else self.dvs_cols

    @property
    def height(self) -> int:
        return self.dvs_cols if self.dvs_swap else self.dvs_rows

    @property
    def aps_width(self) -> int:
        return self._aps.width

    @property
    def aps_height(self) -> int:
        return self._aps.height

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
        ev2, ctrl_idx, ctrl_t = _kernel.scan(words, self._state, self.dvs_cols, self.dvs_rows, self.dvs_swap)
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
        _kernel.scan(words, probe, self.dvs_cols, self.dvs_rows, False)
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
        self._aps.drop_partial()
        self._imu.drop_partial()

    def _control(self, cw: np.ndarray, ct: np.ndarray, out: "_Out") -> bool:
        gap = False
        aps = self._aps
        ns = np.flatnonzero((cw >> 12) != 4)  # every control word that is not an APS sample
        runs = column_runs(cw, ns)
        prev = 0
        k, n = 0, ns.shape[0]
        ns_list = ns.tolist()
        while k < n:
            j = ns_list[k]
            if k in runs and aps.between_columns:
                k_end, length = runs[k]  # k .. k_end: complete columns of one type and one length
                aps.column_block(cw, ns[k:k_end + 1:2], int(cw[j]) - 11, length)
                prev = ns_list[k_end + 1] + 1
                k = k_end + 2
                continue
            if j > prev:
                aps.samples(cw[prev:j])
            prev = j + 1
            w = int(cw[j])
            code, data, t = w >> 12, w & 0xFFF, int(ct[j])
            if code == 0:
                gap |= self._special(data, t, out)
            elif code == 5:
                self._misc8((data >> 8) & 0xF, data & 0xFF)
            # code 6 (misc10: exposure in ADC cycles, for auto-exposure) is not needed
            k += 1
        if prev < cw.shape[0]:
            aps.samples(cw[prev:])
        return gap

    def _special(self, data: int, t: int, out: "_Out") -> bool:
        if data == 1:  # timestamp reset
            self.counters["timestamp_resets"] += 1
            had_data = self.counters["events"] > 0 or self._aps.seq > 0
            self._drop_partial()
            if had_data:
                out.triggers.append((t, TRIGGER_TIMESTAMP_RESET))
            return had_data
        if data in TRIGGER_OF_SPECIAL:
            out.triggers.append((t, TRIGGER_OF_SPECIAL[data]))
        elif data == 5:
            self._imu.start()
        elif data == 7:
            sample = self._imu.end(t)
            if sample is not None:
                out.imu.append(sample)
        elif data in (8, 9):
            self._aps.frame_start(t)
        elif data == 10:
            frame = self._aps.frame_end(t)
            if frame is not None:
                out.frames.append(frame)
        elif data in (11, 12):
            self._aps.column_start(data - 11)
        elif data == 13:
            self._aps.column_end()
        elif data == 14:
            self._aps.exposure_start(t)
        elif data == 15:
            self._aps.exposure_end(t)
        elif data in (0, 6) or data > 17:
            self.counters["bad_words"] += 1
        return False

    def _misc8(self, sub: int, byte: int) -> None:
        if sub == 0:
            self._imu.byte(byte)
        elif sub in (1, 2):
            self._aps.roi_byte(sub, byte)
        elif sub == 3:
            self._imu.configure(byte)
        else:
            self.counters["bad_words"] += 1


class _Out:
    __slots__ = ("frames", "imu", "triggers")

    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self.imu: list = []
        self.triggers: list = []
