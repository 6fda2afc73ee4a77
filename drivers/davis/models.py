"""Per-model facts for the supported DAVIS cameras: USB IDs, chip IDs, sizes, the firmware/logic gate and the
default biases in libcaer's order. Pure data, no I/O.

Sources: inivation/libcaer `src/davis.h`, `include/libcaer/devices/davis.h`, `src/davis_common.h`
(`davisCommonSendDefaultChipConfig`), summarised in the project's davis-usb-protocol note §2, §4.8, §6.
"""

from __future__ import annotations

from dataclasses import dataclass

from edi_live.datatypes import ColorFilter

VENDOR_ID = 0x152A
PID_FX2 = 0x841B  # DAVIS240A/B/C boards (USB 2.0)
PID_FX3 = 0x841A  # DAVIS346 and other FX3 boards (USB 3.0)
DATA_ENDPOINT = 0x82
INTERFACE = 0
CONFIGURATION = 1

LOGIC_VERSION = 18
LOGIC_MIN_PATCH = 1
FIRMWARE_VERSION = {PID_FX2: 4, PID_FX3: 6}  # bcdDevice & 0xFF, exact match (libcaer 3.2 .. 3.3.9)

CHIP_NAMES = {0: "DAVIS240A", 1: "DAVIS240B", 2: "DAVIS240C", 3: "DAVIS128", 4: "DAVIS346A", 5: "DAVIS346B",
              6: "DAVIS640", 7: "DAVIS640H", 8: "DAVIS208", 9: "DAVIS346C"}
DAVIS240_CHIPS = (0, 1, 2)
DAVIS346_CHIPS = (4, 5, 9)

# APS/COLOR_FILTER register (libcaer reads it once at open into info.apsColorFilter and tags every frame with it) ->
# our pattern names. libcaer's codes are its caer_frame_event_color_filter (include/libcaer/events/frame.h); it names
# the 2x2 block clockwise from the top-left (top-left, top-right, bottom-right, bottom-left), we name it row by row:
# its pixel-colour table (src/frame_utils.c, determinePixelColor) puts RGBG's R at (x even, y even), G at (odd, even)
# and (even, odd), B at (odd, odd), i.e. our RGGB, and its OpenCV demosaic uses COLOR_BayerBG2RGB for RGBG, which is
# OpenCV's name for an RGGB sensor. Codes 5..8 are RGBW variants (white instead of the second green): not supported.
LIBCAER_COLOR_FILTERS: dict[int, ColorFilter | None] = {0: None, 1: "RGGB", 2: "GRBG", 3: "GBRG", 4: "BGGR"}
LIBCAER_FILTER_NAMES = {0: "MONO", 1: "RGBG", 2: "GRGB", 3: "GBGR", 4: "BGRG", 5: "RGBW", 6: "GRWB", 7: "WBGR",
                        8: "BWRG"}


def color_filter_of_code(code: int) -> ColorFilter | None:
    """Our pattern for a libcaer colour-filter code; ValueError for a code edi-live cannot use (RGBW, unknown)."""
    if code not in LIBCAER_COLOR_FILTERS:
        name = LIBCAER_FILTER_NAMES.get(code, "unknown")
        raise ValueError(f"APS colour filter code {code} ({name}) is not a supported Bayer pattern "
                         "(edi-live reads mono and RGGB/GRBG/GBRG/BGGR sensors)")
    return LIBCAER_COLOR_FILTERS[code]


def code_of_color_filter(pattern: ColorFilter | None) -> int:
    """The libcaer colour-filter code of our pattern (None = mono = 0); the emulator answers it."""
    return next(code for code, p in LIBCAER_COLOR_FILTERS.items() if p == pattern)


FLASHY_HINT = ("update the camera with iniVation's Flashy tool (https://inivation.gitlab.io/dv/dv-docs/docs/"
               "firmware-update/): it installs FX2 firmware 4 / FX3 firmware 6 and logic 18.1")


def coarse_fine(coarse: int, fine: int, *, n_type: bool, cascode: bool = False, enabled: bool = True,
                low_current: bool = False) -> int:
    """libcaer's coarse-fine current bias word: bit0 enabled, bit1 N-type, bit2 normal (not cascode),
    bit3 normal current level, bits 11..4 fine, bits 14..12 coarse."""
    if not (0 <= coarse <= 7 and 0 <= fine <= 255):
        raise ValueError(f"coarse must be 0..7 and fine 0..255 (got {coarse}/{fine})")
    return (int(enabled) | int(n_type) << 1 | int(not cascode) << 2 | int(not low_current) << 3
            | fine << 4 | coarse << 12)


def shifted_source(ref: int, reg: int, *, mode: int = 0, level: int = 0) -> int:
    """Shifted-source bias word: bits 1..0 mode (0 shifted source, 1 hi-Z, 2 tied to rail), bits 3..2 voltage
    level, bits 9..4 refValue, bits 15..10 regValue."""
    return (mode & 3) | (level & 3) << 2 | (ref & 0x3F) << 4 | (reg & 0x3F) << 10


def vdac(voltage: int, current: int) -> int:
    """VDAC voltage bias word (DAVIS346 family): bits 5..0 voltage (1/64 of 3.3 V), bits 8..6 current."""
    return (voltage & 0x3F) | (current & 7) << 6


def _n(c: int, f: int, **kw: bool) -> int:
    return coarse_fine(c, f, n_type=True, **kw)


def _p(c: int, f: int, **kw: bool) -> int:
    return coarse_fine(c, f, n_type=False, **kw)


# (bias parameter address, 16-bit value) in the order libcaer writes them.
DAVIS240_BIASES: tuple[tuple[int, int], ...] = (
    (0, _n(4, 39)), (1, _n(5, 255)), (2, _n(4, 0)), (3, _n(5, 185, cascode=True)), (4, _n(5, 115, cascode=True)),
    (5, _n(6, 219)), (6, _n(5, 164)), (7, _n(6, 144)), (8, _p(2, 58)), (9, _p(1, 16)), (10, _p(4, 25)),
    (11, _n(6, 91)), (12, _n(5, 49)), (13, _p(4, 80)), (14, _p(7, 152)), (15, _n(5, 255)), (16, _n(5, 255)),
    (17, _n(7, 215)), (18, _n(6, 253)), (19, _n(5, 254)), (20, shifted_source(1, 33)), (21, shifted_source(1, 33)),
)
DAVIS346_BIASES: tuple[tuple[int, int], ...] = (
    (0, vdac(27, 6)), (1, vdac(21, 6)), (2, vdac(32, 7)), (3, vdac(1, 7)), (4, vdac(21, 7)),
    (8, _n(5, 164)), (9, _n(7, 215, enabled=False)), (10, _n(4, 39)), (11, _n(5, 255)), (12, _n(4, 1)),
    (13, _n(6, 144)), (14, _p(2, 58)), (15, _p(1, 16)), (16, _p(4, 25)), (17, _p(6, 20)), (18, _n(6, 219)),
    (19, _p(5, 20)), (20, _n(0, 1)), (21, _p(6, 60)), (22, _n(5, 49)), (23, _n(6, 91)), (24, _p(4, 80)),
    (25, _p(7, 152)), (26, _n(5, 255)), (27, _n(5, 255)), (34, _n(5, 254)), (35, shifted_source(1, 33)),
    (36, shifted_source(1, 33)),
)

# Chip shift-register options (BIAS module, param >= 128); 142 (global shutter) is appended at open time.
DAVIS240_CHIP_CONFIG: tuple[tuple[int, int], ...] = (
    (128, 0), (129, 0), (130, 0), (131, 0), (132, 0), (133, 0), (134, 0), (135, 0), (136, 1), (137, 0), (138, 1),
    (140, 0), (141, 0),
)
DAVIS346_CHIP_CONFIG: tuple[tuple[int, int], ...] = DAVIS240_CHIP_CONFIG + ((143, 1), (144, 0))


@dataclass(frozen=True)
class DavisModel:
    """What the driver and the emulator need to know about one camera model."""

    name: str            # "davis240" / "davis346" (CLI spelling)
    product_id: int
    chip_id: int         # the chip the emulator presents by default
    width: int
    height: int
    firmware: int
    max_packet_bytes: int
    biases: tuple[tuple[int, int], ...]
    chip_config: tuple[tuple[int, int], ...]
    adc_x2: bool         # DAVIS240 external-ADC quirk: samples are doubled on the host

    @property
    def chip_name(self) -> str:
        return CHIP_NAMES[self.chip_id]


DAVIS240 = DavisModel("davis240", PID_FX2, 2, 240, 180, FIRMWARE_VERSION[PID_FX2], 512, DAVIS240_BIASES,
                      DAVIS240_CHIP_CONFIG, True)
DAVIS346 = DavisModel("davis346", PID_FX3, 5, 346, 260, FIRMWARE_VERSION[PID_FX3], 1024, DAVIS346_BIASES,
                      DAVIS346_CHIP_CONFIG, False)
MODELS = {"davis240": DAVIS240, "davis346": DAVIS346}
MODEL_BY_PID = {DAVIS240.product_id: DAVIS240, DAVIS346.product_id: DAVIS346}


def camera_name(chip_id: int) -> str:
    """The camera name users and DV see: "DAVIS346" for every DAVIS346 variant, "DAVIS240A/B/C" as is."""
    name = CHIP_NAMES.get(chip_id, f"chip{chip_id}")
    return "DAVIS346" if chip_id in DAVIS346_CHIPS else name


def model_for_chip(chip_id: int) -> DavisModel | None:
    """The model profile (biases, quirks) for a chip ID read from SYSINFO, or None if unsupported."""
    if chip_id in DAVIS240_CHIPS:
        return DAVIS240
    if chip_id in DAVIS346_CHIPS:
        return DAVIS346
    return None


def get_model(name: str) -> DavisModel:
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown DAVIS model {name!r} (expected one of {sorted(MODELS)})") from None
