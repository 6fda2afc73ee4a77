"""The data contract every stage speaks: events, frames, IMU, triggers, packets and reconstructions.

Time is always int64 microseconds on the sensor clock (for recordings: Unix µs as stored in AEDAT4).
Events use one structured dtype everywhere. Its layout is AEDAT4's 16-byte event record
(t at byte 0, x at 8, y at 10, polarity at 12), so a decompressed EVTS buffer is viewed without a copy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

EVENT_DTYPE = np.dtype(
    {
        "names": ["t", "x", "y", "p"],
        "formats": ["<i8", "<u2", "<u2", "?"],
        "offsets": [0, 8, 10, 12],
        "itemsize": 16,
    }
)
"""t: µs (int64), x/y: pixel column/row (uint16), p: polarity, True = ON (brighter)."""

IMU_DTYPE = np.dtype(
    [
        ("t", "<i8"),
        ("temperature_c", "<f4"),
        ("accel_g", "<f4", (3,)),
        ("gyro_dps", "<f4", (3,)),
        ("mag_ut", "<f4", (3,)),
    ]
)
"""One IMU sample: accelerometer in g, gyroscope in °/s, magnetometer in µT, temperature in °C."""

TRIGGER_DTYPE = np.dtype([("t", "<i8"), ("type", "i1")])
"""One trigger. `type` follows AEDAT4's TriggerType enum (6/7 = APS frame start/end, 8/9 = exposure start/end)."""


ColorFilter = Literal["RGGB", "GRBG", "GBRG", "BGGR"]
"""A Bayer colour-filter pattern, named by its top-left 2x2 block read row by row (so "RGGB": R at (0, 0), G at
(0, 1) and (1, 0), B at (1, 1)). None stands for a monochrome sensor."""
COLOR_FILTERS: tuple[ColorFilter, ...] = ("RGGB", "GRBG", "GBRG", "BGGR")


def empty_events(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=EVENT_DTYPE)


def as_events(events: np.ndarray) -> np.ndarray:
    """`events` in EVENT_DTYPE exactly (the same array when it already is). Arrays with the same fields in another
    layout, such as the packed 13-byte dtype numpy's own np.concatenate makes of EVENT_DTYPE, are converted."""
    if events.dtype == EVENT_DTYPE:
        return events
    if events.dtype.names is None or not set(EVENT_DTYPE.names) <= set(events.dtype.names):
        raise TypeError(f"events need the fields {EVENT_DTYPE.names} (got dtype {events.dtype})")
    out = np.empty(len(events), EVENT_DTYPE)
    for name in EVENT_DTYPE.names:
        out[name] = events[name]
    return out


def concat_events(parts: Sequence[np.ndarray]) -> np.ndarray:
    """The events of `parts`, in order, as one new EVENT_DTYPE array (use instead of np.concatenate).

    np.concatenate of structured arrays with padding returns a packed dtype with the same fields, and copies field
    by field (~10x slower); here the records are copied as raw int64 pairs, at memcpy speed.
    """
    raw = [np.ascontiguousarray(as_events(p)).view(np.int64) for p in parts]
    if not raw:
        return empty_events()
    return np.concatenate(raw).view(EVENT_DTYPE)


def empty_imu(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=IMU_DTYPE)


def empty_triggers(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=TRIGGER_DTYPE)


@dataclass(frozen=True, slots=True)
class Frame:
    """One APS (intensity) frame with its exposure window.

    `image` is (height, width), row-major, uint8 or uint16: gray, or a raw Bayer mosaic when `color_filter` names
    its pattern; or (height, width, 3) uint8/uint16 BGR when the source delivers demosaiced colour. B is the mean of
    the latent image over [exposure_start_us, exposure_end_us]. `start_us`/`end_us` are the readout start/end when
    known.
    """

    image: np.ndarray
    exposure_start_us: int
    exposure_end_us: int
    start_us: int | None = None
    end_us: int | None = None
    seq: int = 0
    color_filter: ColorFilter | None = None

    def __post_init__(self) -> None:
        if not (self.image.ndim == 2 or (self.image.ndim == 3 and self.image.shape[2] == 3)):
            raise ValueError(f"Frame.image must be (h, w) or (h, w, 3) BGR (got shape {self.image.shape})")
        if self.color_filter is not None and self.image.ndim != 2:
            raise ValueError("a Frame with a colour-filter pattern holds the raw 2-D mosaic, not BGR")
        if self.exposure_end_us < self.exposure_start_us:
            raise ValueError(
                f"Frame exposure ends before it starts (got {self.exposure_start_us}..{self.exposure_end_us} µs)"
            )

    @property
    def exposure_us(self) -> int:
        return self.exposure_end_us - self.exposure_start_us

    @property
    def mid_exposure_us(self) -> int:
        return (self.exposure_start_us + self.exposure_end_us) // 2

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])


@dataclass(slots=True)
class Packet:
    """What a source hands on in one step, in time order.

    Ordering contract (live and replay alike): `events` are sorted by t. Every event with
    t <= frame.exposure_end_us of a frame in this packet is in this packet or an earlier one, so a
    consumer may deblur a frame as soon as it sees it. `watermark_us` promises that no later packet holds
    an event with t < watermark_us. `gap` is True when data was lost just before this packet (drops),
    so reconstruction state spanning the gap is unreliable. `arrival_ns` is host time.monotonic_ns()
    when the data reached the host (for latency).
    """

    events: np.ndarray = field(default_factory=empty_events)
    frames: list[Frame] = field(default_factory=list)
    imu: np.ndarray = field(default_factory=empty_imu)
    triggers: np.ndarray = field(default_factory=empty_triggers)
    watermark_us: int = -(2**63)
    arrival_ns: int = 0
    gap: bool = False


@dataclass(frozen=True, slots=True)
class SourceInfo:
    """What a source says about the camera it stands for."""

    width: int
    height: int
    name: str = "unknown"  # e.g. "DAVIS346" or "DAVIS240C"
    serial: str = ""
    kind: Literal["usb", "replay", "emulator", "network"] = "replay"
    color_filter: ColorFilter | None = None
    """The sensor's Bayer pattern for a colour camera (e.g. a colour DAVIS346), None for monochrome."""

    @property
    def is_color(self) -> bool:
        return self.color_filter is not None

    @property
    def label(self) -> str:
        """Camera name and serial as users see them, e.g. 'DAVIS346_00000391'."""
        return f"{self.name}_{self.serial}" if self.serial else self.name


@dataclass(slots=True)
class SourceStatus:
    """Counters a source exposes; read from any thread (values are plain ints)."""

    packets: int = 0
    events: int = 0
    frames: int = 0
    dropped_bytes: int = 0
    dropped_events: int = 0
    gaps: int = 0
    backlog: int = 0


Kind = Literal["deblurred", "latent"]


@dataclass(frozen=True, slots=True)
class Reconstruction:
    """One sharp frame produced by the EDI worker.

    `image` is (height, width) uint8 gray or (height, width, 3) uint8 BGR (a colour camera's output, demosaiced),
    display-ready and owned by the receiver (a copy, never a view
    of reconstructor state); linear intensity on the 8-bit APS scale, above the APS black level (an APS frame of
    this scene would read black_level + 255 * (image / 255) ** (1 / aps_gamma)). `t_us` the latent time,
    `ref_t_us` the reference time f of the APS frame it derives from, `exposure_*` that APS frame's exposure
    window (in the event clock). `c_on`/`c_off` are the thresholds used (equal when a single c is used). `n_events` counts events since the previous emitted reconstruction.
    `arrival_ns` is the host arrival time of the last event included (for latency).
    """

    image: np.ndarray
    t_us: int
    kind: Kind
    ref_t_us: int
    exposure_start_us: int
    exposure_end_us: int
    c_on: float
    c_off: float
    n_events: int
    arrival_ns: int = 0
    black_level: float = 0.0
    aps_gamma: float = 1.0
