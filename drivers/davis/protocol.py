"""The logic-18 register protocol as data: module/parameter addresses, 0xBF/0xC2 vendor-request packing,
clock-unit conversions, and the configure / start / stop sequences as lists of (module, param, value).

No I/O here: `device.py` sends these through a transport, and the emulator decodes the same packing.
Source: inivation/libcaer `include/libcaer/devices/davis.h`, `src/usb_utils.h`, `src/davis.c`
(davis-usb-protocol note §3-§5).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

from drivers.davis.models import DavisModel
from edi_live.errors import ConfigError

REQ_OUT = 0x40  # vendor, device, host-to-device
REQ_IN = 0xC0   # vendor, device, device-to-host
VR_CONFIG = 0xBF           # one parameter: wValue = module, wIndex = param, 4-byte big-endian u32
VR_CONFIG_MULTIPLE = 0xC2  # wValue = N entries of (module u8, param u8, value u32 BE)

MUX, DVS, APS, IMU, EXTINPUT, BIAS, SYSINFO, USB = 0, 1, 2, 3, 4, 5, 6, 9

# MUX
MUX_RUN, MUX_TIMESTAMP_RUN, MUX_TIMESTAMP_RESET, MUX_RUN_CHIP = 0, 1, 2, 3
MUX_DROP_EXTINPUT_ON_STALL, MUX_DROP_DVS_ON_STALL = 4, 5
MUX_HAS_STATISTICS, MUX_STAT_DVS_DROPPED = 80, 83
# DVS
DVS_SIZE_COLUMNS, DVS_SIZE_ROWS, DVS_ORIENTATION, DVS_RUN, DVS_WAIT_ON_STALL = 0, 1, 2, 3, 4
DVS_HAS_PIXEL_FILTER, DVS_HAS_BA_FILTER, DVS_HAS_ROI_FILTER = 10, 30, 40
DVS_HAS_SKIP_FILTER, DVS_HAS_POLARITY_FILTER = 50, 60
# APS
APS_SIZE_COLUMNS, APS_SIZE_ROWS, APS_ORIENTATION, APS_COLOR_FILTER, APS_RUN, APS_WAIT_ON_STALL = 0, 1, 2, 3, 4, 5
APS_HAS_GLOBAL_SHUTTER, APS_GLOBAL_SHUTTER = 6, 7
APS_START_COLUMN, APS_START_ROW, APS_END_COLUMN, APS_END_ROW = 8, 9, 10, 11
APS_EXPOSURE, APS_FRAME_INTERVAL = 12, 13
# IMU
IMU_TYPE, IMU_ORIENTATION, IMU_RUN_ACCEL, IMU_RUN_GYRO, IMU_RUN_TEMP = 0, 1, 2, 3, 4
IMU_SAMPLE_RATE_DIVIDER, IMU_ACCEL_DLPF, IMU_ACCEL_FULL_SCALE, IMU_GYRO_DLPF, IMU_GYRO_FULL_SCALE = 5, 6, 7, 9, 10
# EXTINPUT
EXTINPUT_RUN_DETECTOR, EXTINPUT_DETECT_PULSE_LENGTH = 0, 5
# BIAS/CHIP
CHIP_GLOBAL_SHUTTER = 142
# SYSINFO
SYS_LOGIC_VERSION, SYS_CHIP_ID, SYS_IS_MASTER, SYS_LOGIC_CLOCK, SYS_ADC_CLOCK, SYS_USB_CLOCK = 0, 1, 2, 3, 4, 5
SYS_CLOCK_DEVIATION, SYS_LOGIC_PATCH = 6, 7
# USB
USB_RUN, USB_EARLY_PACKET_DELAY = 0, 1

EXPOSURE_MAX_US = 4_194_303
FRAME_INTERVAL_MAX_US = 8_388_607
DEFAULT_EXPOSURE_US = 4000
DEFAULT_FRAME_INTERVAL_US = 40000

Write = tuple[int, int, int]  # (module, param, value)


def pack_value(value: int) -> bytes:
    """The 4-byte data stage of a 0xBF write (big-endian u32)."""
    return struct.pack(">I", value & 0xFFFFFFFF)


def unpack_value(data: bytes | Sequence[int]) -> int:
    if len(data) != 4:
        raise ValueError(f"a register read must return 4 bytes (got {len(data)})")
    return struct.unpack(">I", bytes(data))[0]


def unpack_multiple(count: int, data: bytes) -> list[Write]:
    """The entries of a 0xC2 batched write's data stage: N x (module u8, param u8, value u32 BE), no padding.
    The driver never batches (libcaer's start sequence needs no 0xC2); the emulator accepts it like a device."""
    if len(data) != 6 * count:
        raise ValueError(f"0xC2 batch of {count} entries needs {6 * count} bytes (got {len(data)})")
    return [struct.unpack_from(">BBI", data, 6 * i) for i in range(count)]


@dataclass(frozen=True)
class Clocks:
    """Clocks read from SYSINFO; actual MHz = nominal x deviation / 1000."""

    logic_mhz: float
    adc_mhz: float
    usb_mhz: float

    @classmethod
    def from_registers(cls, logic: int, adc: int, usb: int, deviation: int) -> "Clocks":
        f = (deviation or 1000) / 1000.0
        return cls(logic * f, adc * f, usb * f)


def us_to_cycles(us: int, clock_mhz: float) -> int:
    return int(round(us * clock_mhz))


def cycles_to_us(cycles: int, clock_mhz: float) -> int:
    return int(round(cycles / clock_mhz)) if clock_mhz > 0 else 0


def check_exposure(exposure_us: int | None, frame_interval_us: int | None) -> None:
    """The APS timing registers' ranges; a value outside is a usage error (ConfigError, exit 2 in the CLI)."""
    for flag, value, top, register in (("exposure-us", exposure_us, EXPOSURE_MAX_US, "APS exposure"),
                                       ("frame-interval-us", frame_interval_us, FRAME_INTERVAL_MAX_US,
                                        "APS frame interval")):
        if value is not None and not 0 <= value <= top:
            # "at most": the CLI asks for a positive value before this check, so a bound of 0 would contradict it
            bound = f"at most {top} µs" if value > top else f"0..{top} µs"
            raise ConfigError(f"{flag} must be {bound}, the {register} register's range (got {value})")


def dvs_filter_defaults(features: dict[int, int], columns: int, rows: int) -> list[Write]:
    """libcaer's DVS filter defaults for the filters the logic reports (`features`: HAS_* param -> value):
    pixel filters parked off-array, background-activity filter on (8 x 250 µs = 2 ms), refractory off,
    ROI = whole array, skip and polarity filters off."""
    w: list[Write] = []
    if features.get(DVS_HAS_PIXEL_FILTER):
        for i in range(8):
            w += [(DVS, 11 + 2 * i, rows), (DVS, 12 + 2 * i, columns)]
    if features.get(DVS_HAS_BA_FILTER):
        w += [(DVS, 31, 1), (DVS, 32, 8), (DVS, 33, 0), (DVS, 34, 1)]
    if features.get(DVS_HAS_ROI_FILTER):
        w += [(DVS, 41, 0), (DVS, 42, 0), (DVS, 43, columns - 1), (DVS, 44, rows - 1)]
    if features.get(DVS_HAS_SKIP_FILTER):
        w += [(DVS, 51, 0), (DVS, 52, 5)]
    if features.get(DVS_HAS_POLARITY_FILTER):
        w += [(DVS, 61, 0), (DVS, 62, 0), (DVS, 63, 0)]
    return w


def default_config(model: DavisModel, *, has_global_shutter: bool, aps_columns: int, aps_rows: int,
                   clocks: Clocks, exposure_us: int = DEFAULT_EXPOSURE_US,
                   frame_interval_us: int = DEFAULT_FRAME_INTERVAL_US, dvs_features: dict[int, int] | None = None,
                   dvs_columns: int = 0, dvs_rows: int = 0) -> list[Write]:
    """libcaer's sendDefaultConfig: biases, chip options, FPGA defaults, then the USB early-packet delay."""
    gs = int(has_global_shutter)
    writes: list[Write] = [(BIAS, p, v) for p, v in model.biases]
    writes += [(BIAS, p, v) for p, v in model.chip_config] + [(BIAS, CHIP_GLOBAL_SHUTTER, gs)]
    writes += [(MUX, MUX_TIMESTAMP_RESET, 0), (MUX, MUX_DROP_EXTINPUT_ON_STALL, 1), (MUX, MUX_DROP_DVS_ON_STALL, 1),
               (DVS, DVS_WAIT_ON_STALL, 0)]
    writes += dvs_filter_defaults(dvs_features or {}, dvs_columns, dvs_rows)
    writes += [
        (APS, APS_WAIT_ON_STALL, 1), (APS, APS_GLOBAL_SHUTTER, gs),
        (APS, APS_START_COLUMN, 0), (APS, APS_START_ROW, 0),
        (APS, APS_END_COLUMN, aps_columns - 1), (APS, APS_END_ROW, aps_rows - 1),
        (APS, APS_EXPOSURE, us_to_cycles(exposure_us, clocks.adc_mhz)),
        (APS, APS_FRAME_INTERVAL, us_to_cycles(frame_interval_us, clocks.adc_mhz)),
        (IMU, IMU_SAMPLE_RATE_DIVIDER, 0), (IMU, IMU_ACCEL_DLPF, 1), (IMU, IMU_ACCEL_FULL_SCALE, 1),
        (IMU, IMU_GYRO_DLPF, 1), (IMU, IMU_GYRO_FULL_SCALE, 1),
        # external input: detect 10 µs high pulses only
        (EXTINPUT, 1, 0), (EXTINPUT, 2, 0), (EXTINPUT, 3, 1), (EXTINPUT, 4, 1),
        (EXTINPUT, EXTINPUT_DETECT_PULSE_LENGTH, us_to_cycles(10, clocks.logic_mhz)),
        (USB, USB_EARLY_PACKET_DELAY, us_to_cycles(8 * 125, clocks.usb_mhz)),  # 1 ms
    ]
    return writes


PRODUCERS_OFF: list[Write] = [(DVS, DVS_RUN, 0), (APS, APS_RUN, 0), (IMU, IMU_RUN_ACCEL, 0), (IMU, IMU_RUN_GYRO, 0),
                              (IMU, IMU_RUN_TEMP, 0), (EXTINPUT, EXTINPUT_RUN_DETECTOR, 0)]
MUX_OFF: list[Write] = [(MUX, MUX_RUN, 0), (MUX, MUX_TIMESTAMP_RUN, 0), (USB, USB_RUN, 0), (MUX, MUX_RUN_CHIP, 0)]
# libcaer's dataStart: all off, sleep 10 ms, clear_halt, start reader, chip on, sleep 200 ms, USB+MUX on, sleep
# 50 ms, producers on. No timestamp reset: libcaer sends none (the MUX reset pulse is for syncing several
# cameras); the driver anchors device time to the host clock when the MUX starts (DavisDecoder.anchor).
START_ALL_OFF: list[Write] = PRODUCERS_OFF + MUX_OFF
START_CHIP_ON: list[Write] = [(MUX, MUX_RUN_CHIP, 1)]
START_MUX_ON: list[Write] = [(USB, USB_RUN, 1), (MUX, MUX_TIMESTAMP_RUN, 1), (MUX, MUX_RUN, 1)]
START_PRODUCERS_ON: list[Write] = [(DVS, DVS_RUN, 1), (APS, APS_RUN, 1), (IMU, IMU_RUN_ACCEL, 1),
                                   (IMU, IMU_RUN_GYRO, 1), (IMU, IMU_RUN_TEMP, 1), (EXTINPUT, EXTINPUT_RUN_DETECTOR, 1)]
STOP_SEQUENCE: list[Write] = PRODUCERS_OFF + MUX_OFF
START_SLEEPS_S = {"drain": 0.010, "chip": 0.200, "mux": 0.050}
