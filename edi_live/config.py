"""Node configuration: frozen, validated dataclasses, built from flags and/or a TOML file.

The TOML file uses the same keys as the command-line flags (without the leading dashes; `-` or `_` both work),
all at the top level, for example::

    replay = "rec.aedat4"
    speed = 0
    every = 1000
    c-on = 0.2
    c-off = 0.25
    publish = ["tcp://127.0.0.1:5555"]
    out = "sharp.aedat4"

Precedence: built-in defaults < the TOML file < explicit flags (`merge_options`). Every invalid value raises
`ConfigError` naming the key and the bad value "(got ...)".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from edi_live import config_file
from edi_live.checks import check as _check
from edi_live.datatypes import COLOR_FILTERS
from edi_live.checks import check_endpoint, fits_memory, int_in as _int_in, parse_tcp_endpoint
from edi_live.checks import check_ports_apart, positive_or_none as _positive_or_none
from edi_live.config_file import as_bool as _bool, as_endpoints as _endpoints, as_number as _num, as_path as _path
from edi_live.config_file import merge_options, norm_key
from edi_live.errors import ConfigError
from edi_live.file_roles import check_apart

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"
POLICIES = ("drop_oldest", "wait")
MODES = ("causal", "nearest", "fused")
DEVICE_MODELS = ("davis240", "davis346", "auto")
LOG_LEVELS = ("debug", "info", "warning", "error")

MIN_HEARTBEAT_S = 0.001
"""Shortest keyframe interval: below it a still scene's heartbeat came on almost every event (1e-300 s gave
416k frames for a 0.3 s recording)."""


# the bounds of the camera values, as options and in a saved calibration (edi_live.calibration checks it against them)
C_RANGE = (0.01, 2.0)  # a contrast threshold
APS_GAMMA_RANGE = (0.2, 5.0)
BLACK_LEVEL_END = 128  # a black level is in [0, BLACK_LEVEL_END) DN
CLOCK_OFFSET_MAX_US = 100_000  # events lag the APS clock by at most this many µs, either way
EVENT_BYTES = 16  # one ring slot (EVENT_DTYPE)


@dataclass(frozen=True)
class SourceConfig:
    """Where the data comes from: a live device (`device`) or a recording (`replay`)."""

    device: str | None = None  # davis240 | davis346 | auto
    replay: Path | None = None
    serial: str | None = None
    exposure_us: int | None = None
    frame_interval_us: int | None = None
    reconnect: bool = False
    usb_backend: str | None = None  # MODULE:CALLABLE
    emulate_from: Path | None = None
    speed: float = 1.0  # 1 = real time, 0 = as fast as possible
    loop: bool = False
    dv_input: tuple[str, ...] = ()  # DV network outputs, one endpoint per stream ([TYPE=]tcp://HOST:PORT)

    def __post_init__(self) -> None:
        _check(not self.dv_input or (self.device is None and self.replay is None),
               f"choose one input: --dv-input, --device or --replay (got dv-input={list(self.dv_input)!r})")
        _check(self.device is None or self.replay is None,
               f"choose one input: device or replay (got device={self.device!r} and replay={str(self.replay)!r})")
        _check(self.device is None or self.device in DEVICE_MODELS,
               f"device must be one of {', '.join(DEVICE_MODELS)} (got {self.device!r})")
        _check(isinstance(self.speed, (int, float)) and not isinstance(self.speed, bool)
               and math.isfinite(self.speed) and self.speed >= 0,
               f"speed must be >= 0, 1 = real time, 0 = as fast as possible (got {self.speed!r})")
        for name in ("exposure_us", "frame_interval_us"):
            value = getattr(self, name)
            _check(value is None or (isinstance(value, int) and value > 0),
                   f"{name.replace('_', '-')} must be a positive integer in µs (got {value!r})")
        _check(self.usb_backend is None or (isinstance(self.usb_backend, str) and ":" in self.usb_backend
                                            and all(self.usb_backend.split(":", 1))),
               f"usb-backend must look like MODULE:CALLABLE (got {self.usb_backend!r})")
        _check(self.emulate_from is None or self.usb_backend is not None,
               "emulate-from needs --usb-backend, e.g. --usb-backend drivers.emulator:backend")
        _check(self.loop is False or self.replay is not None or self.emulate_from is not None,
               "loop applies to --replay or --emulate-from only")

    @property
    def kind(self) -> str:
        return "replay" if self.replay is not None else ("dv" if self.dv_input else "device")


@dataclass(frozen=True)
class RingConfig:
    """The event ring and APS frame queue between the pump and the worker."""

    capacity_events: int = 1 << 22  # 64 MiB of 16-byte events; half is kept as exposure history
    capacity_frames: int = 16
    policy: str | None = None  # None: "wait" for replay, "drop_oldest" for a live device

    def __post_init__(self) -> None:
        _check(isinstance(self.capacity_events, int) and not isinstance(self.capacity_events, bool)
               and self.capacity_events >= 1024, f"ring-events must be an integer >= 1024 (got {self.capacity_events!r})")
        fits_memory("ring-events", self.capacity_events, EVENT_BYTES, "4194304 = 64 MiB")
        _int_in("ring-frames", self.capacity_frames, 1, 10**6, "APS frames the ring holds")
        _check(self.policy is None or self.policy in POLICIES,
               f"ring-policy must be one of {', '.join(POLICIES)} (got {self.policy!r})")


@dataclass(frozen=True)
class EdiConfig:
    """What the worker emits and how the reconstructor gets its contrast threshold."""

    every: int = 1000  # emit a latent frame every N events
    every_ms: float = 2.0  # ... or at the first event this much sensor time after the previous frame (0: events only)
    c: float | None = None  # fixed threshold for both polarities
    c_on: float | None = None
    c_off: float | None = None
    mode: str = "causal"
    max_fps: float | None = None
    heartbeat_s: float = 1.0  # keyframe interval on a static scene
    reestimate_every: int = 0  # re-estimate c every K APS frames (0: only when the cached c stops fitting)
    # causal mode: deblur APS frames on a helper thread while latent frames keep flowing (lower latency, ~25 %
    # less throughput). None = automatic: on for a live camera and paced replay, off for --speed 0.
    deblur_thread: bool | None = None
    deblur_ahead: bool = True  # run the next exposure's double integral while it is exposed (exposure_ahead.py)
    # ignore pixels that flicker at a mains period (flicker_pixels.py); None: on, except in fused mode (its next frame
    # already takes a lamp's drift out, and the mask would cost it 0.3 dB on the realistic simulator)
    flicker_mask: bool | None = None
    fused_residual: bool = True  # fused mode: estimate the log change below one threshold between events
    divisor_median: bool = True  # deblur with the 3x3 median of log D (edi/smoothing.py); False: per-pixel EDI
    latent_denoise: bool = False  # causal latent frames: lone changes since te not shown (edi/lone.py)
    aps_gamma: float | None = None  # APS response exponent; None: 1, or a loaded calibration's
    # events arrive this many µs later than the APS exposure they belong to; None: estimated (from a calibration's)
    clock_offset_us: int | None = None
    # the live prediction figure (edi_live.quality): score one APS frame in N; 0 = off
    quality_every: int = 2
    # APS black level (8-bit DN) taken off each frame so the output is linear; None: estimated from the stream
    # (starting from a loaded calibration's)
    black_level: float | None = None
    # per-pixel noise rates (edi_live.pixel_noise): estimated from the stream unless off, or given as one rate
    # (ON + OFF, Hz per pixel)
    noise_stats: bool = True
    noise_rate_hz: float | None = None
    # a saved calibration (edi_live.calibration.Calibration, set by the node) whose c, black level, clock offset and
    # noise rates the estimates start from
    start: Any = field(default=None, compare=False, repr=False)
    gray: bool = False  # a colour source's frames as grey (h, w) images
    # the Bayer pattern of a colour source: --bayer-pattern, else the source's own (SourceInfo.color_filter)
    color_filter: str | None = None

    def __post_init__(self) -> None:
        _int_in("every", self.every, 1, 10**12, "events per latent frame")
        _check(isinstance(self.every_ms, (int, float)) and not isinstance(self.every_ms, bool)
               and math.isfinite(self.every_ms) and 0 <= self.every_ms <= 3_600_000,
               f"every-ms must be a number of milliseconds in [0, 3600000]; 0 = by event count only "
               f"(got {self.every_ms!r})")
        for name in ("c", "c_on", "c_off"):
            value = getattr(self, name)
            _check(value is None or (isinstance(value, (int, float)) and C_RANGE[0] <= value <= C_RANGE[1]),
                   f"{name.replace('_', '-')} must be a contrast threshold in [{C_RANGE[0]:g}, {C_RANGE[1]:g}] "
                   f"(got {value!r})")
        _check((self.c_on is None) == (self.c_off is None),
               f"c-on and c-off go together (got c-on={self.c_on!r}, c-off={self.c_off!r})")
        _check(self.c is None or self.c_on is None,
               f"use either c or c-on/c-off (got c={self.c!r}, c-on={self.c_on!r})")
        _check(self.mode in MODES, f"mode must be one of {', '.join(MODES)} (got {self.mode!r})")
        _positive_or_none("max-fps", self.max_fps)
        _positive_or_none("heartbeat-s", self.heartbeat_s, wait=True)
        _check(self.heartbeat_s >= MIN_HEARTBEAT_S,
               f"heartbeat-s must be at least {MIN_HEARTBEAT_S:g} s (got {self.heartbeat_s!r}): it is the keyframe "
               f"interval of a still scene; for frames at a steady rate use --every-ms")
        _int_in("reestimate-every", self.reestimate_every, 0, 10**9, "APS frames; 0 = only when c stops fitting")
        _int_in("quality-every", self.quality_every, 0, 10**6, "score one APS frame in N; 0 = off")
        _check(self.aps_gamma is None or (isinstance(self.aps_gamma, (int, float))
                                          and not isinstance(self.aps_gamma, bool)
                                          and math.isfinite(self.aps_gamma)
                                          and APS_GAMMA_RANGE[0] <= self.aps_gamma <= APS_GAMMA_RANGE[1]),
               f"aps-gamma must be a number in [{APS_GAMMA_RANGE[0]:g}, {APS_GAMMA_RANGE[1]:g}] "
               f"(got {self.aps_gamma!r})")
        if self.clock_offset_us is not None:
            _int_in("clock-offset-us", self.clock_offset_us, -CLOCK_OFFSET_MAX_US, CLOCK_OFFSET_MAX_US,
                    "µs the events lag the APS clock")
        _check(self.black_level is None or (isinstance(self.black_level, (int, float))
                                            and not isinstance(self.black_level, bool)
                                            and math.isfinite(self.black_level)
                                            and 0 <= self.black_level < BLACK_LEVEL_END),
               f"black-level must be a number of DN in [0, {BLACK_LEVEL_END}) (got {self.black_level!r})")
        _check(self.color_filter is None or self.color_filter in COLOR_FILTERS,
               f"bayer-pattern must be one of {', '.join(COLOR_FILTERS)} (got {self.color_filter!r})")
        _check(isinstance(self.deblur_ahead, bool), f"deblur-ahead must be true or false (got {self.deblur_ahead!r})")
        _check(self.flicker_mask is None or isinstance(self.flicker_mask, bool),
               f"flicker-mask must be true or false (got {self.flicker_mask!r})")
        for key in ("fused_residual", "divisor_median", "latent_denoise"):
            _check(isinstance(getattr(self, key), bool),
                   f"{key.replace('_', '-')} must be true or false (got {getattr(self, key)!r})")
        _check(isinstance(self.noise_stats, bool), f"noise-stats must be true or false (got {self.noise_stats!r})")
        _check(self.noise_rate_hz is None or (isinstance(self.noise_rate_hz, (int, float))
                                              and not isinstance(self.noise_rate_hz, bool)
                                              and math.isfinite(self.noise_rate_hz) and 0 <= self.noise_rate_hz <= 1e6),
               f"noise-rate-hz must be a rate in Hz per pixel in [0, 1e6] (got {self.noise_rate_hz!r})")
        _check(self.deblur_thread is None or isinstance(self.deblur_thread, bool),
               f"deblur-thread must be true or false (got {self.deblur_thread!r})")


@dataclass(frozen=True)
class PublisherConfig:
    """The ZeroMQ PUB endpoints (empty when publishing is off)."""

    endpoints: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    curve_secret_key: Path | None = None
    stats_interval_s: float = 1.0

    def __post_init__(self) -> None:
        for endpoint in self.endpoints:
            check_endpoint(endpoint)
        _positive_or_none("stats-interval-s", self.stats_interval_s, wait=True)

    @property
    def enabled(self) -> bool:
        return bool(self.endpoints)


@dataclass(frozen=True)
class OutputConfig:
    """Files written while running: reconstructed frames (`out`) and the raw input (`record`)."""

    out: Path | None = None
    record: Path | None = None
    dv_output: str | None = None  # tcp://HOST:PORT: the sharp frames as a DV network stream
    dv_output_events: str | None = None  # tcp://HOST:PORT: the input events passed through, as a DV stream
    queue_items: int = 256  # bounded writer queues; the producer waits (lossless)

    def __post_init__(self) -> None:
        _check(isinstance(self.queue_items, int) and self.queue_items >= 1,
               f"writer queue size must be >= 1 (got {self.queue_items!r})")
        _check(self.out is None or self.record is None or Path(self.out) != Path(self.record),
               f"out and record must be different files (got {str(self.out)!r} twice)")
        for flag, endpoint in (("--dv-output", self.dv_output), ("--dv-output-events", self.dv_output_events)):
            if endpoint is not None:  # here, before the node warns that the endpoint is exposed
                parse_tcp_endpoint(endpoint, flag)


@dataclass(frozen=True)
class NodeConfig:
    source: SourceConfig = field(default_factory=SourceConfig)
    ring: RingConfig = field(default_factory=RingConfig)
    edi: EdiConfig = field(default_factory=EdiConfig)
    publisher: PublisherConfig = field(default_factory=PublisherConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    duration_s: float | None = None
    log_level: str = "info"
    status_interval_s: float | None = None  # None: 0.5 s live line on a TTY, 5 s plain lines otherwise
    calibration: Path | None = None  # a saved calibration to start from (edi_live.calibration)
    save_calibration: Path | None = None  # where to save the calibration in use at the end

    def __post_init__(self) -> None:
        check_apart({"replay": self.source.replay, "emulate-from": self.source.emulate_from,
                     "calibration": self.calibration, "curve-secret-key": self.publisher.curve_secret_key},
                    {"out": self.output.out, "record": self.output.record, "save-calibration": self.save_calibration},
                    may_update={"save-calibration": "calibration"})
        check_ports_apart([("--publish", e) for e in self.publisher.endpoints]
                          + [(f, e) for f, e in (("--dv-output", self.output.dv_output),
                                                 ("--dv-output-events", self.output.dv_output_events)) if e])
        _positive_or_none("duration", self.duration_s)
        _positive_or_none("status-interval-s", self.status_interval_s)
        _check(self.log_level in LOG_LEVELS,
               f"log-level must be one of {', '.join(LOG_LEVELS)} (got {self.log_level!r})")

    @property
    def ring_policy(self) -> str:
        """The effective overflow policy: lossless waiting for replay, never blocking for a live device."""
        if self.ring.policy is not None:
            return self.ring.policy
        if self.source.kind == "replay" or self.source.emulate_from is not None:
            return "wait"  # a recording (direct or through the emulated camera) can always wait
        return "drop_oldest"

    @property
    def effective_edi(self) -> EdiConfig:
        """`edi` with the automatic choices made: the deblur thread is on unless replaying as fast as possible
        (where throughput matters and latency means nothing)."""
        if self.edi.deblur_thread is not None:
            return self.edi
        unpaced = self.source.kind == "replay" and self.source.speed == 0
        return dataclasses.replace(self.edi, deblur_thread=not unpaced)

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> "NodeConfig":
        """Build from a flat mapping of flag names (as in the TOML file) to values."""
        opts = {norm_key(k): v for k, v in options.items()}
        unknown = sorted(set(opts) - set(OPTION_KEYS))
        _check(not unknown, f"unknown option(s) {', '.join(unknown)} (valid keys: {', '.join(sorted(OPTION_KEYS))})")
        try:
            return _build(opts)
        except TypeError as exc:  # a wrong type that a comparison tripped over
            raise ConfigError(f"invalid option value ({exc})") from exc

    @classmethod
    def from_toml(cls, path: str | Path, overrides: Mapping[str, Any] | None = None) -> "NodeConfig":
        """Read `path`, then apply `overrides` (explicit flags) on top."""
        return cls.from_options(merge_options(read_toml(path), overrides or {}))


# flat option key -> (section, field, converter)
OPTION_KEYS: dict[str, tuple[str, str, Any]] = {
    "device": ("source", "device", None),
    "replay": ("source", "replay", _path),
    "serial": ("source", "serial", lambda v: None if v is None else str(v)),
    "exposure_us": ("source", "exposure_us", None),
    "frame_interval_us": ("source", "frame_interval_us", None),
    "reconnect": ("source", "reconnect", _bool("reconnect")),
    "usb_backend": ("source", "usb_backend", None),
    "emulate_from": ("source", "emulate_from", _path),
    "speed": ("source", "speed", _num),
    "loop": ("source", "loop", _bool("loop")),
    "ring_events": ("ring", "capacity_events", None),
    "ring_frames": ("ring", "capacity_frames", None),
    "ring_policy": ("ring", "policy", None),
    "every": ("edi", "every", None),
    "every_ms": ("edi", "every_ms", _num),
    "c": ("edi", "c", _num),
    "c_on": ("edi", "c_on", _num),
    "c_off": ("edi", "c_off", _num),
    "mode": ("edi", "mode", None),
    "max_fps": ("edi", "max_fps", _num),
    "heartbeat_s": ("edi", "heartbeat_s", _num),
    "reestimate_every": ("edi", "reestimate_every", None),
    "quality_every": ("edi", "quality_every", None),
    "black_level": ("edi", "black_level", _num),
    "clock_offset_us": ("edi", "clock_offset_us", None),
    "aps_gamma": ("edi", "aps_gamma", _num),
    "deblur_thread": ("edi", "deblur_thread", None),
    "deblur_ahead": ("edi", "deblur_ahead", _bool("deblur-ahead")),
    "flicker_mask": ("edi", "flicker_mask", _bool("flicker-mask")),
    "fused_residual": ("edi", "fused_residual", _bool("fused-residual")),
    "divisor_median": ("edi", "divisor_median", _bool("divisor-median")),
    "latent_denoise": ("edi", "latent_denoise", _bool("latent-denoise")),
    "noise_stats": ("edi", "noise_stats", _bool("noise-stats")),
    "noise_rate_hz": ("edi", "noise_rate_hz", _num),
    "gray": ("edi", "gray", _bool("gray")),
    "bayer_pattern": ("edi", "color_filter", lambda v: None if v is None else str(v).upper()),
    "publish": ("publisher", "endpoints", _endpoints),
    "no_publish": ("publisher", "-", _bool("no-publish")),
    "curve_secret_key": ("publisher", "curve_secret_key", _path),
    "stats_interval_s": ("publisher", "stats_interval_s", _num),
    "dv_input": ("source", "dv_input", _endpoints),
    "dv_output": ("output", "dv_output", lambda v: None if v is None else str(v)),
    "dv_output_events": ("output", "dv_output_events", lambda v: None if v is None else str(v)),
    "out": ("output", "out", _path),
    "record": ("output", "record", _path),
    "duration": ("node", "duration_s", _num),
    "log_level": ("node", "log_level", lambda v: str(v).lower()),
    "status_interval_s": ("node", "status_interval_s", _num),
    "calibration": ("node", "calibration", _path),
    "save_calibration": ("node", "save_calibration", _path),
}


def _build(opts: dict[str, Any]) -> NodeConfig:
    sections: dict[str, dict[str, Any]] = {"source": {}, "ring": {}, "edi": {}, "publisher": {}, "output": {},
                                           "node": {}}
    for key, value in opts.items():
        section, name, convert = OPTION_KEYS[key]
        if convert is not None:
            try:
                value = convert(value)
            except (TypeError, ValueError, OverflowError) as exc:  # e.g. float(10**400), Path(3)
                raise ConfigError(f"{key.replace('_', '-')}: {exc} (got {value!r})") from None
        if name != "-":
            sections[section][name] = value
    if opts.get("no_publish"):
        if "publish" in opts:
            raise ConfigError(f"publish and no-publish contradict each other (got publish={opts['publish']!r} "
                              f"and no-publish); give one of them")
        sections["publisher"]["endpoints"] = ()
    return NodeConfig(
        source=SourceConfig(**sections["source"]),
        ring=RingConfig(**sections["ring"]),
        edi=EdiConfig(**sections["edi"]),
        publisher=PublisherConfig(**sections["publisher"]),
        output=OutputConfig(**sections["output"]),
        **sections["node"],
    )



def read_toml(path: str | Path) -> dict[str, Any]:
    """The flat option mapping of a TOML config file (edi_live.config_file), checked against OPTION_KEYS."""
    return config_file.read_toml(path, OPTION_KEYS)

__all__ = ["DEFAULT_ENDPOINT", "LOG_LEVELS", "MODES", "OPTION_KEYS", "EdiConfig", "NodeConfig", "merge_options",
           "read_toml"]
