"""APS frame assembly for the DAVIS word decoder: column words in, `Frame`s out.

Owns the state of the frame being read out: its start, exposure start/end, the ROI sent with it, and the reset
and signal columns collected so far. `drivers.davis.decoder.DavisDecoder` dispatches the special and misc words to
it (frame start/end, column start/end, exposure start/end, ROI bytes) and hands it the sample words. A frame is
emitted only when both readouts are complete (else it is counted in `frames_dropped`); pixels are the correlated
double sample reset - signal with libcaer's white-pixel rule (davis-usb-protocol note, APS section).
"""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import ColorFilter, Frame

APS_ADC_MAX = 1023
WHITE_RESET_MIN = 384


def column_runs(cw: np.ndarray, ns: np.ndarray) -> dict[int, tuple[int, int]]:
    """Runs of complete columns (start 11/12, samples, end 13) of one type and one length among the control
    words `cw`, whose non-sample words are at `ns`. Keyed by the index in `ns` of the first column start:
    {k: (index of the last column start, samples per column)}. They are decoded as one 2-D block instead of
    word by word."""
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


class ApsFrameAssembler:
    """The APS frame in progress. `aps_columns`/`aps_rows` are the SIZE registers; `swap`, `flip_x`, `flip_y`
    the ORIENTATION_INFO bits; `adc_x2` doubles samples (DAVIS240); `frame_bits` 8 gives uint8 frames
    (ADC >> 2, like DV recordings), 16 gives uint16 (ADC << 6). Counts into `counters` ("frames",
    "frames_dropped"). `color_filter` tags every frame with the sensor's Bayer pattern (None: mono), as libcaer
    does: the pattern is the register's, not shifted for orientation or ROI."""

    def __init__(self, aps_columns: int, aps_rows: int, *, swap: bool, flip_x: bool, flip_y: bool, adc_x2: bool,
                 frame_bits: int, counters: dict[str, int], color_filter: ColorFilter | None = None) -> None:
        self.cols, self.rows = int(aps_columns), int(aps_rows)
        self.swap, self.flip_x, self.flip_y = swap, flip_x, flip_y
        self.adc_x2 = adc_x2
        self.frame_bits = frame_bits
        self.counters = counters
        self.color_filter = color_filter
        self.seq = 0  # frames emitted
        self.ignore = True  # until the first frame start (stale data at startup)
        self._roi = [0, 0, self.width - 1, self.height - 1]
        self._roi_tmp = 0
        self._roi_update = 0
        self.frame: dict | None = None
        self.col_type = -1  # readout of the column in progress: 0 reset, 1 signal, -1 none
        self._col_parts: list[np.ndarray] = []

    @property
    def width(self) -> int:
        return self.rows if self.swap else self.cols

    @property
    def height(self) -> int:
        return self.cols if self.swap else self.rows

    @property
    def between_columns(self) -> bool:
        """A frame is being read and no column is open: a run of whole columns may be decoded as a block."""
        return self.frame is not None and not self.ignore and self.col_type < 0

    def drop_partial(self) -> None:
        """Data was lost or time was reset: the frame in progress is dropped, samples ignored until a frame start."""
        if self.frame is not None:
            self.counters["frames_dropped"] += 1
        self.frame = None
        self.col_type = -1
        self._col_parts = []
        self.ignore = True

    def frame_start(self, t: int) -> None:
        if self.frame is not None:
            self.counters["frames_dropped"] += 1
        self.ignore = False
        self._roi_update = 0
        self.frame = {"start": t, "exp_start": None, "exp_end": None, "count": [0, 0], "cols": [[], []]}
        self.col_type = -1

    def exposure_start(self, t: int) -> None:
        if self.frame is not None:
            self.frame["exp_start"] = t

    def exposure_end(self, t: int) -> None:
        if self.frame is not None:
            self.frame["exp_end"] = t

    def roi_byte(self, sub: int, byte: int) -> None:
        """misc8 sub 1 (high byte) / sub 2 (low byte, completes a value): start column, start row, end column,
        end row, in turn."""
        if sub == 1:
            self._roi_tmp = byte << 8
        else:
            self._roi[self._roi_update & 3] = self._roi_tmp | byte
            self._roi_update += 1

    def column_start(self, readout: int) -> None:
        """Special 11 (readout 0, reset read) or 12 (readout 1, signal read)."""
        if not self.ignore:
            self.col_type = readout
            self._col_parts = []

    def samples(self, s: np.ndarray) -> None:
        if self.ignore or self.frame is None or self.col_type < 0:
            return
        self._col_parts.append(s & 0x3FF)

    def column_block(self, cw: np.ndarray, col_starts: np.ndarray, readout: int, length: int) -> None:
        """Whole columns of one readout at once: each starts at a word of `col_starts` and holds `length`
        samples (see column_runs)."""
        f = self.frame
        ex, ey, _, _ = self._expected()
        take = min(col_starts.shape[0], ex - f["count"][readout])
        if take <= 0:
            return
        idx = col_starts[:take, None] + 1 + np.arange(min(length, ey))
        f["cols"][readout].append(cw[idx] & 0x3FF)
        f["count"][readout] += take

    def column_end(self) -> None:
        f = self.frame
        if self.ignore or f is None or self.col_type < 0:
            return
        ex, ey, _, _ = self._expected()
        r = self.col_type
        col = np.concatenate(self._col_parts) if self._col_parts else np.zeros(0, np.uint16)
        self._col_parts = []
        self.col_type = -1
        if f["count"][r] < ex:
            f["cols"][r].append(col[None, :ey])
            f["count"][r] += 1

    def frame_end(self, t: int) -> Frame | None:
        """The finished frame, or None if there was none or it is incomplete (then counted as dropped)."""
        f = self.frame
        if self.ignore or f is None:
            return None
        self.frame = None
        ex, ey, w, h = self._expected()
        if f["count"][0] != ex or f["count"][1] != ex:
            self.counters["frames_dropped"] += 1
            return None
        reset, signal = (_assemble(f["cols"][r], ex, ey) for r in (0, 1))
        if self.adc_x2:
            reset <<= 1
            signal <<= 1
        pix = np.clip(reset - signal, 0, APS_ADC_MAX)
        pix[(reset < WHITE_RESET_MIN) | (signal == 0)] = APS_ADC_MAX
        if self.flip_x:
            pix = pix[::-1, :]
        if self.flip_y:
            pix = pix[:, ::-1]
        img = pix if self.swap else pix.T
        img = (img >> 2).astype(np.uint8) if self.frame_bits == 8 else (img << 6).astype(np.uint16)
        es = f["exp_start"] if f["exp_start"] is not None else f["start"]
        ee = f["exp_end"] if f["exp_end"] is not None else t
        ee = max(ee, es)
        frame = Frame(np.ascontiguousarray(img), int(es), int(ee), int(f["start"]), int(t), self.seq,
                      color_filter=self.color_filter)
        self.seq += 1
        self.counters["frames"] += 1
        return frame

    def _expected(self) -> tuple[int, int, int, int]:
        x0, y0, x1, y1 = self._roi
        w, h = x1 + 1 - x0, y1 + 1 - y0
        if w <= 0 or h <= 0 or x1 >= self.width or y1 >= self.height:
            w, h = self.width, self.height
        return (h, w, w, h) if self.swap else (w, h, w, h)


def _assemble(cols: list[np.ndarray], ex: int, ey: int) -> np.ndarray:
    a = np.zeros((ex, ey), dtype=np.int32)  # missing samples read as 0 -> white, like an unwritten pixel
    i = 0
    for block in cols:  # 2-D blocks of whole columns
        a[i:i + block.shape[0], : block.shape[1]] = block
        i += block.shape[0]
    return a
