"""Deblurring one APS frame: B as float, log L(f) = log B - log D, and the single-pass divisor for one c.

Intensities are on the 8-bit APS scale (0..255, linear); times are int64 µs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from edi_live.edi import _backend, _kernels_pixels, _kernels_stream
from edi_live.edi._backend import DARK_FLOOR, LOG_MAX, LOG_MIN
from edi_live.edi.latent import render_buckets, to_uint8, u8_tables
from edi_live.edi.levels import LevelTable, build_level_table, log_divisor
from edi_live.edi.selection import window


@dataclass(frozen=True)
class ApsResponse:
    """How APS values relate to light: value = black_level + 255 * (I / 255) ** (1 / gamma), clipped at
    `saturation` (default: full scale of the image's dtype), on the 8-bit scale. EDI needs B linear in I."""

    saturation: float | None = None
    black_level: float = 0.0
    gamma: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.black_level) and 0.0 <= self.black_level < 128.0):
            raise ValueError(f"black level must be in [0, 128) DN on the 8-bit scale (got {self.black_level!r})")
        if not (math.isfinite(self.gamma) and 0.2 <= self.gamma <= 5.0):
            raise ValueError(f"APS gamma must be in [0.2, 5] (got {self.gamma!r})")

    @property
    def linear(self) -> bool:
        return self.black_level == 0.0 and self.gamma == 1.0

    def to_float(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return blurry_to_float(image, saturation=self.saturation, black_level=self.black_level, gamma=self.gamma)


def blurry_to_float(image: np.ndarray, *, saturation: float | None = None, black_level: float = 0.0,
                    gamma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """APS image (uint8/uint16/float) -> (B on the 8-bit scale as float32, informative mask).

    `black_level` (8-bit scale) is the APS value of no light and `gamma` the response's exponent (see ApsResponse):
    both are undone, so that B is linear in intensity. A pixel is uninformative when it is at or below the black
    level or at/above `saturation` (default: full scale of the dtype): a clipped value does not equal the mean of
    the latent intensity, so dividing it would be wrong.
    """
    img = np.asarray(image)
    if (black_level or gamma != 1.0) and img.dtype == np.uint8 and _backend.have_numba() \
            and isinstance(black_level, (int, float)):
        # 256 values: what the formulas below give each, looked up (~25 µs at 240x180 against 41 with a black
        # level, 113 with a gamma; a linear frame's two numpy passes take ~20)
        lut_b, lut_informative = _u8_float_tables(None if saturation is None else float(saturation), black_level,
                                                  float(gamma))
        b, informative = np.empty(img.shape, np.float32), np.empty(img.shape, bool)
        _kernels_pixels.lookup_u8(np.ascontiguousarray(img).reshape(-1), lut_b, lut_informative, b.reshape(-1),
                                  informative.reshape(-1))
        return b, informative
    return _blurry_to_float(img, saturation, black_level, gamma)


@functools.lru_cache(maxsize=64, typed=True)  # typed: a float64 black level compares B in float64, a float in float32
def _u8_float_tables(saturation: float | None, black_level: float, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """blurry_to_float's (B, informative) for each uint8 value 0..255, by its formulas (read-only: shared)."""
    tables = _blurry_to_float(np.arange(256, dtype=np.uint8), saturation, black_level, gamma)
    for t in tables:
        t.setflags(write=False)
    return tables


def _blurry_to_float(img: np.ndarray, saturation: float | None, black_level: float,
                     gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """blurry_to_float with numpy (the reference of the table look-up for non-linear uint8 frames)."""
    if black_level or gamma != 1.0:
        b, informative = _blurry_to_float(img, saturation, 0.0, 1.0)
        informative &= b > black_level
        b -= np.float32(black_level)
        np.maximum(b, 0.0, out=b)
        if gamma != 1.0:
            b = (np.float32(255.0) * (b / np.float32(255.0)) ** np.float32(gamma)).astype(np.float32)
        return b, informative
    if img.dtype == np.uint8:
        # the general path below gives exactly this: B = img (scale 1), always finite and >= 0
        sat = 255.0 if saturation is None else float(saturation)
        return img.astype(np.float32), (img > 0) & (img < sat)
    if img.dtype == np.uint16:
        full = 65535.0
    else:
        full = 255.0
    sat = full if saturation is None else float(saturation)
    b = img.astype(np.float32) * np.float32(255.0 / full)
    with np.errstate(invalid="ignore"):
        informative = (img > 0) & (img < sat) & np.isfinite(b)
    b = np.nan_to_num(b, nan=0.0, posinf=255.0, neginf=0.0)
    np.clip(b, 0.0, None, out=b)
    return b, informative


def deblur_log(blurry: np.ndarray, table: LevelTable | None, c_on: float, c_off: float | None = None, *,
               informative: np.ndarray | None = None,
               divisor: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """log L(f) on the 8-bit scale, (H, W) float32: log B - log D at active informative pixels, log B elsewhere.

    `blurry` is B as float (8-bit scale, see blurry_to_float); `informative` defaults to 0 < B < 255.
    log D comes from `table` at (c_on, c_off), or precomputed as `divisor` = (pixels, log D, ...).
    """
    b = np.asarray(blurry, dtype=np.float32)
    if table is not None and b.shape != (table.height, table.width):
        raise ValueError(f"blurry image shape {b.shape} does not match the table ({table.height}, {table.width})")
    out = np.log(np.maximum(b, DARK_FLOOR)).reshape(-1)
    if divisor is None and table is not None and table.n_active:
        divisor = (table.pixels, log_divisor(table, c_on, c_off))
    if divisor is not None and divisor[0].size:
        pix, ld = divisor[0], divisor[1]
        if informative is None:
            bp = b.reshape(-1)[pix]
            use = (bp > 0) & (bp < 255.0)
        else:
            use = informative.reshape(-1)[pix]
        out[pix[use]] -= ld[use].astype(np.float32)
    np.clip(out, LOG_MIN, LOG_MAX, out=out)
    return out.reshape(b.shape)


def deblur(blurry: np.ndarray, table: LevelTable, c_on: float, c_off: float | None = None, *,
           informative: np.ndarray | None = None, max_value: float = 4 * 255.0) -> np.ndarray:
    """Sharp L(f) = B / D(c), float32 (H, W) on the 8-bit scale, finite, clipped to [0, max_value]."""
    out = np.exp(deblur_log(blurry, table, c_on, c_off, informative=informative))
    np.clip(out, 0.0, max_value, out=out)
    return out


def log_divisor_events(events: np.ndarray, width: int, height: int, exposure_start_us: int, exposure_end_us: int,
                       ref_t_us: int | None, c_on: float, c_off: float | None = None, *,
                       mask: np.ndarray | None = None,
                       event_counts: np.ndarray | None = None,
                       counts_after_f: tuple[np.ndarray, np.ndarray] | None = None) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(active pixels, log D, exponent change f->te or None) for ONE c straight from the events.

    Same log D as log_divisor(build_level_table(...)) but, with the kernels, a single pass without sorting, which
    also yields c * E(f -> te) per active pixel (so the latent image at te costs O(pixels)).
    Pixel order is unspecified. `mask`/`event_counts` as in build_level_table. `counts_after_f` (flat int64
    n_on, n_off): when the single pass runs (the third result is not None), it adds the ON/OFF counts of the
    unmasked events in (f, te] to them, which saves the caller a second pass; otherwise they are left alone.
    """
    c_off = c_on if c_off is None else c_off
    ts, te = int(exposure_start_us), int(exposure_end_us)
    if te < ts:
        raise ValueError(f"exposure ends before it starts (got {ts}..{te} µs)")
    f = (ts + te) // 2 if ref_t_us is None else min(max(int(ref_t_us), ts), te)
    if _backend.have_numba() and 0 < te - ts < 2**24:  # float32 times in the pass are exact
        ev = window(events, ts, te)
        m, use_m = _backend.mask_arg(mask)
        cnt = _backend.NO_COUNTS if event_counts is None else event_counts
        acc_on, acc_off = counts_after_f if counts_after_f is not None else (_backend.NO_COUNTS, _backend.NO_COUNTS)
        npix = width * height
        if c_on == c_off:
            return _kernels_stream.divisor_stream(ev["t"], ev["x"], ev["y"], ev["p"], width, height, m, use_m, ts, te,
                                                  f, float(c_on), cnt, event_counts is not None,
                                                  np.empty(npix, _kernels_stream.DIVISOR_STATE),
                                                  np.zeros(npix, np.uint8), acc_on, acc_off,
                                                  counts_after_f is not None)
        return _kernels_stream.divisor_stream_two(ev["t"], ev["x"], ev["y"], ev["p"], width, height, m, use_m, ts, te,
                                                  f, float(c_on), float(c_off), cnt, event_counts is not None,
                                                  np.empty(npix, _kernels_stream.DIVISOR_STATE_TWO),
                                                  np.zeros(npix, np.uint8), acc_on, acc_off,
                                                  counts_after_f is not None)
    table = build_level_table(events, width, height, ts, te, f, mask=mask, segments=c_on != c_off,
                              event_counts=event_counts)
    return table.pixels, log_divisor(table, c_on, c_off), None


def finish_frame_u8(image: np.ndarray, saturation: float, divisor: tuple[np.ndarray, np.ndarray, np.ndarray],
                    log_ref: np.ndarray, deblurred: np.ndarray, log_lat: np.ndarray, display: np.ndarray, *,
                    black_level: float = 0.0, gamma: float = 1.0,
                    shown: tuple[np.ndarray, np.ndarray] | None = None, log_shown: np.ndarray | None = None) -> None:
    """What follows the divisor of a uint8 APS frame, into the given (H, W) arrays: log L(f) (log B minus log D
    at the active informative pixels, clipped) and its uint8 image; the latent log image at te (L(f) plus the
    f -> te exponent of `divisor`, from log_divisor_events) and its uint8 image, B linearised with `black_level`
    and `gamma` (see blurry_to_float). One pass with the kernels.

    `shown` = (log D, f -> te jump) per active pixel to show instead (smoothing.smoothed_divisor): the uint8 image
    of L(f), `log_shown` (its log image; required with `shown`, apart from log_ref) and the latent image at te come
    from it, while log_ref keeps each pixel's own log L(f)."""
    pixels, log_d, delta_end = divisor
    if delta_end is None or (shown is not None and shown[1] is None):
        raise ValueError("finish_frame_u8 needs the f -> te exponent (log_divisor_events with counts_after_f)")
    if shown is not None and (log_shown is None or np.shares_memory(log_shown, log_ref)):
        raise ValueError("finish_frame_u8 with `shown` needs a log_shown array apart from log_ref for the L(f) it "
                         "shows")
    shown_d, shown_jump = (log_d, delta_end) if shown is None else shown
    log_shown = log_ref if log_shown is None else log_shown
    if _backend.have_numba():
        lut_log, lut_u8 = u8_tables(float(black_level), float(gamma))
        _kernels_stream.finish_frame_u8(np.ascontiguousarray(image).reshape(-1), float(saturation),
                                        float(black_level), lut_log, lut_u8, pixels, log_d, shown_d, shown_jump,
                                        np.float32(LOG_MIN), np.float32(LOG_MAX), log_ref.reshape(-1),
                                        log_shown.reshape(-1), deblurred.reshape(-1), log_lat.reshape(-1),
                                        display.reshape(-1), *render_buckets())
        return
    b, informative = blurry_to_float(image, saturation=saturation, black_level=black_level, gamma=gamma)
    own, shown_log, lat = reference_logs(b, informative, pixels, log_d,
                                         None if log_shown is log_ref else shown_d, shown_jump)
    log_ref[...] = own
    if log_shown is not log_ref:
        log_shown[...] = shown_log
    deblurred[...] = to_uint8(shown_log)
    log_lat[...] = lat
    display[...] = to_uint8(log_lat)


def reference_logs(b: np.ndarray, informative: np.ndarray, pixels: np.ndarray, log_d: np.ndarray,
                   shown_d: np.ndarray | None = None, jump: np.ndarray | None = None) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """With numpy, for any frame (B as float, blurry_to_float): (log L(f) of each pixel's own log D, log L(f) of the
    log D shown, or the first array itself without `shown_d`, the latent log image at te: the shown one plus `jump`
    at the active pixels, clipped, or a copy of it without a jump). finish_frame_u8's numpy reference and the
    reconstructor's path for other frames."""
    own = deblur_log(b, None, 1.0, informative=informative, divisor=(pixels, log_d))
    shown = own if shown_d is None else deblur_log(b, None, 1.0, informative=informative, divisor=(pixels, shown_d))
    lat = shown.copy()
    if jump is not None:
        flat = lat.reshape(-1)
        flat[pixels] += np.asarray(jump).astype(np.float32)
        np.clip(flat, LOG_MIN, LOG_MAX, out=flat)
    return own, shown, lat


def fall_back_u8(pixels: np.ndarray, image: np.ndarray, black_level: float, gamma: float, log_ref: np.ndarray,
                 log_lat: np.ndarray, display: np.ndarray, deblurred: np.ndarray) -> None:
    """At `pixels` ((H, W) bool) of a uint8 frame, in place: log_ref and log_lat = clipped log(max(B linearised,
    floor)), display and deblurred = its uint8 image, from u8_tables (what finish_frame_u8 gives a pixel without
    events). All (H, W) C-contiguous."""
    lut_log, lut_u8 = u8_tables(float(black_level), float(gamma))
    if _backend.have_numba():
        _kernels_pixels.fall_back_u8(np.ascontiguousarray(pixels, bool).reshape(-1),
                                     np.ascontiguousarray(image).reshape(-1), lut_log, lut_u8, log_ref.reshape(-1),
                                     log_lat.reshape(-1), display.reshape(-1), deblurred.reshape(-1))
        return
    idx = np.flatnonzero(pixels)
    values = image.reshape(-1)[idx]
    for out, table in ((log_ref, lut_log), (log_lat, lut_log), (display, lut_u8), (deblurred, lut_u8)):
        out.reshape(-1)[idx] = table[values]
