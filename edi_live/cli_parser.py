"""The `edi-live` command line's flags: their groups, units, defaults and help, the examples, and how to see the
frames. Parsing errors are one-line ConfigErrors (exit 2), not argparse's usage block."""

from __future__ import annotations

import argparse
from typing import Any

from edi_live import __version__
from edi_live.config import DEFAULT_ENDPOINT, LOG_LEVELS
from edi_live.errors import ConfigError

PROG = "edi-live"

EXAMPLES = f"""\
examples:
  # replay a recording as fast as possible, publish on {DEFAULT_ENDPOINT}, save the sharp frames
  edi-live --replay rec.aedat4 --speed 0 --every 1000 --out sharp.aedat4

  # a live DAVIS346 with a fixed contrast threshold, 500 latent frames/s at most, raw input recorded
  edi-live --device davis346 --c 0.2 --max-fps 500 --record raw.aedat4

  # no camera: the built-in emulator replays a recording through the USB driver
  edi-live --device davis240 --usb-backend drivers.emulator:backend --emulate-from rec.aedat4

  # a camera running in DV (two network TCP server outputs: events, frames); sharp frames back to DV
  edi-live --dv-input tcp://127.0.0.1:7777 --dv-input tcp://127.0.0.1:7778 --dv-output tcp://127.0.0.1:7779

seeing the frames:
  python -m edi_live.client      prints what arrives (any program can subscribe: see edi_live/client.py)
  python -m tools.viewer         from a checkout of the repository: live frames and counters at http://127.0.0.1:8080
  --dv-output tcp://HOST:PORT    DV's GUI (network input module) or dv-processing's NetworkReader shows them
  --out FILE.aedat4              opens in DV (file input), dv-processing, or --replay; one 8-bit frame each

Ctrl-C or SIGTERM stops cleanly (files finalised, exit 0; a second Ctrl-C is ignored while it stops). Exit codes: 0 ok, 1 runtime error, 2 usage error.
Every flag but --list-devices, --calibrate-dark and --version can also be set in --config FILE.toml with the
same name (e.g. `every = 1000`, `c-on = 0.2`).
"""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse would print the usage block too)
        raise ConfigError(f"{message} (see {PROG} --help)")


class _Once(argparse.Action):
    """A flag naming an input or a file: given twice with two values, argparse keeps the last in silence (a recording
    not replayed, an --out not written)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        before = getattr(namespace, self.dest, None)
        if before is not None and before != values:
            parser.error(f"{option_string} given twice ({before!r} and {values!r}): give it once")
        setattr(namespace, self.dest, values)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, argument_default=argparse.SUPPRESS, formatter_class=argparse.RawDescriptionHelpFormatter,
                description="Real-time EDI deblurring for DAVIS event cameras: one blurry APS frame plus its events "
                            "become sharp video, streamed over ZeroMQ.",
                epilog=EXAMPLES)
    src = p.add_argument_group("input (one of)")
    src.add_argument("--device", action=_Once, choices=("davis240", "davis346", "auto"),
                     help="a live DAVIS camera over USB ('auto': the first one found)")
    src.add_argument("--replay", action=_Once, metavar="FILE.aedat4",
                     help="replay an AEDAT4 recording as if a camera were attached")
    src.add_argument("--dv-input", action="append", metavar="[TYPE=]tcp://HOST:PORT",
                     help="a DV / dv-processing network output, repeatable: one endpoint per stream (events, frames, "
                          "imu, triggers; the type is read from the stream, a TYPE= prefix asserts it)")
    src.add_argument("--list-devices", action="store_true", help="list attached DAVIS cameras and exit")
    dev = p.add_argument_group("device options")
    dev.add_argument("--serial", metavar="S", help="pick the camera with this serial number")
    dev.add_argument("--exposure-us", type=int, metavar="US", help="APS exposure in µs (default: the camera's)")
    dev.add_argument("--frame-interval-us", type=int, metavar="US",
                     help="time between APS frames in µs (default: the camera's)")
    dev.add_argument("--reconnect", action="store_true", help="after an unplug (or a dropped --dv-input connection), "
                                                               "wait for the camera and resume")
    dev.add_argument("--usb-backend", metavar="MODULE:CALLABLE",
                     help="pyusb backend factory; CALLABLE() returns a usb.backend.IBackend (default: libusb)")
    dev.add_argument("--emulate-from", action=_Once, metavar="FILE.aedat4",
                     help="with --usb-backend drivers.emulator:backend: the recording the emulated camera streams")
    pace = p.add_argument_group("pacing")
    pace.add_argument("--speed", type=float, metavar="X",
                      help="replay speed: 1 = real time (default), 4 = 4x faster, 0 = as fast as possible")
    pace.add_argument("--loop", action="store_true", help="restart the replay at its end (time keeps increasing)")
    pace.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds (default: run "
                                                                         "until the input ends or Ctrl-C)")
    edi = p.add_argument_group("EDI reconstruction")
    edi.add_argument("--every", type=int, metavar="N", help="emit a latent frame every N events (default: 1000)")
    edi.add_argument("--every-ms", type=float, metavar="MS",
                     help="... or at the first event MS ms of sensor time after the previous frame, whichever comes "
                          "first (default: 2; 0 = by event count only)")
    edi.add_argument("--c", type=float, metavar="C", help="fixed contrast threshold for both polarities "
                                                          "(default: estimated, re-estimated when it stops fitting)")
    edi.add_argument("--c-on", type=float, metavar="C", help="fixed ON threshold (with --c-off)")
    edi.add_argument("--c-off", type=float, metavar="C", help="fixed OFF threshold (with --c-on)")
    edi.add_argument("--mode", choices=("causal", "nearest", "fused"),
                     help="causal (default): latent frames from the latest deblurred APS frame, lowest latency; "
                          "nearest: wait for the next APS frame when it is nearer (adds latency, reported); "
                          "fused: every latent frame from both APS frames around it, best quality (waits for "
                          "the next APS frame: up to one frame interval plus half an exposure, reported)")
    edi.add_argument("--max-fps", type=float, metavar="FPS", help="cap on latent frames per second (default: none)")
    edi.add_argument("--heartbeat-s", type=float, metavar="S",
                     help="keyframe interval on a static scene, seconds (default: 1.0)")
    edi.add_argument("--deblur-thread", action=argparse.BooleanOptionalAction,
                     help="causal mode: deblur APS frames on a helper thread so latent frames are not held up "
                          "(default: on, except for --speed 0 replays where throughput matters)")
    edi.add_argument("--deblur-ahead", action=argparse.BooleanOptionalAction,
                     help="accumulate each exposure's double integral while it is exposed, when exposures are "
                          "regular, so a deblurred frame only waits for a finish (default: on; frames are the same)")
    edi.add_argument("--flicker-mask", action=argparse.BooleanOptionalAction,
                     help="ignore the events of pixels that flicker at a mains period (100/120 Hz lamps), so that a "
                          "lamp shows what the APS frames say instead of drifting or blooming (default: on, except "
                          "in fused mode, whose next APS frame already takes the drift out)")
    edi.add_argument("--fused-residual", action=argparse.BooleanOptionalAction,
                     help="--mode fused: also estimate how far each pixel's log intensity has moved towards its next "
                          "event (+1.4 dB on the simulator; 1.4x a causal frame's cost with c estimated, 3.2x with a "
                          "fixed c; default: on)")
    edi.add_argument("--divisor-median", action=argparse.BooleanOptionalAction,
                     help="deblur with the 3x3 median of the double integral's log over neighbouring pixels, not each "
                          "pixel's own, so that one pixel's event errors do not speckle the frame (+2 dB at "
                          "mid-exposure on the simulators; default: on; off: plain per-pixel EDI)")
    edi.add_argument("--latent-denoise", action=argparse.BooleanOptionalAction,
                     help="grey sensors, causal mode: in latent frames, a pixel whose change since the exposure's end "
                          "fewer than 2 of its 8 neighbours share shows its value at the exposure's end, so that one "
                          "pixel's extra or missing event is no dot (redone per frame in the 8x8 tiles near its "
                          "events; 1.3-1.5x the worker's CPU; default: off)")
    edi.add_argument("--reestimate-every", type=int, metavar="K",
                     help="also re-estimate c every K APS frames (default: 0 = only when it stops fitting)")
    edi.add_argument("--black-level", type=float, metavar="DN",
                     help="APS black level in 8-bit DN, taken off every APS frame so that the output is linear in "
                          "intensity (default: estimated from the stream while c is estimated and --aps-gamma is 1, "
                          "else a loaded calibration's or 0)")
    edi.add_argument("--aps-gamma", type=float, metavar="G",
                     help="APS response exponent: value = black level + 255 (I/255)^(1/G); undone before the "
                          "deblur so that the output is linear (default: 1, or a loaded calibration's)")
    edi.add_argument("--clock-offset-us", type=int, metavar="US",
                     help="events arrive this much later than the APS exposure they belong to (pixel latency; the "
                          "EDI authors set it by hand); the exposure window moves into the event clock (default: "
                          "estimated from the stream while c is estimated, else a loaded calibration's or 0)")
    edi.add_argument("--noise-stats", action=argparse.BooleanOptionalAction,
                     help="estimate each pixel's background-activity rate (ON and OFF) where the scene is still, "
                          "shown in the stats and saved with the calibration (default: on while c is estimated)")
    edi.add_argument("--noise-rate-hz", type=float, metavar="HZ",
                     help="give every pixel this noise rate (ON + OFF events per second) instead of estimating it")
    edi.add_argument("--calibration", action=_Once, metavar="FILE",
                     help="start from a saved calibration of this camera (c, black level, clock offset, per-pixel "
                          "noise rates); a live camera "
                          "loads its own from ~/.config/edi-live/calibration/ without this flag")
    edi.add_argument("--save-calibration", action=_Once, metavar="FILE",
                     help="save the calibration in use at the end of the run (a live camera also saves its own)")
    edi.add_argument("--calibrate-dark", type=int, metavar="N",
                     help="measure the APS black level on N dark frames (cover the lens) and write it into the "
                          "calibration (--save-calibration FILE, or a live camera's own file), then exit; later runs "
                          "use it as given")
    edi.add_argument("--gray", action="store_true",
                     help="a colour camera's frames as grey images (default: colour BGR for a colour camera)")
    edi.add_argument("--bayer-pattern", metavar="PATTERN", type=str.upper,
                     help="read the APS frames as a colour mosaic with this Bayer pattern (RGGB, GRBG, GBRG, "
                          "BGGR: the top-left 2x2 block row by row), for a recording that does not name it (DV's "
                          "BGR frames, raw mosaics stored as grey); default: the source's own, RGGB for BGR frames")
    edi.add_argument("--quality-every", type=int, metavar="N",
                     help="score how well the output predicted one APS frame in N (the live quality figure; "
                          "default: 2, 0 = off)")
    out = p.add_argument_group("output")
    out.add_argument("--publish", action="append", metavar="ENDPOINT",
                     help=f"ZeroMQ PUB endpoint, repeatable (default: {DEFAULT_ENDPOINT}; loopback only)")
    out.add_argument("--no-publish", action="store_true", help="do not publish (e.g. only write --out)")
    out.add_argument("--curve-secret-key", action=_Once, metavar="FILE",
                     help="encrypt with CURVE using this server secret key file "
                          "(make one: python -m edi_live.publisher --gen-curve-keys DIR)")
    out.add_argument("--stats-interval-s", type=float, metavar="S",
                     help="period of the [b\"stats\", map] message on the socket, seconds (default: 1.0)")
    out.add_argument("--dv-output", action=_Once, metavar="tcp://HOST:PORT",
                     help="also serve the sharp frames as a DV network stream (AEDAT4 over TCP, as DV's network TCP "
                          "server output and dv-processing's NetworkWriter; loopback unless you choose otherwise)")
    out.add_argument("--dv-output-events", action=_Once, metavar="tcp://HOST:PORT",
                     help="also serve the input events, passed through, as a second DV network stream")
    out.add_argument("--out", action=_Once, metavar="FILE.aedat4",
                     help="also write every emitted frame (8-bit gray, or BGR from a colour camera; lossless)")
    out.add_argument("--record", action=_Once, metavar="FILE.aedat4",
                     help="record the raw input as received, for --replay")
    adv = p.add_argument_group("advanced")
    adv.add_argument("--ring-events", type=int, metavar="N",
                     help="ring capacity in events, half kept as exposure history (default: 4194304 = 64 MiB)")
    adv.add_argument("--ring-frames", type=int, metavar="N", help="APS frames the ring holds (default: 16)")
    adv.add_argument("--ring-policy", choices=("drop_oldest", "wait"),
                     help="overflow policy (default: wait for replay/emulation, drop_oldest for a live camera or "
                          "--dv-input)")
    other = p.add_argument_group("other")
    other.add_argument("--config", action=_Once, metavar="FILE.toml",
                       help="read options from a TOML file; flags override it")
    other.add_argument("--log-level", choices=LOG_LEVELS, help="log verbosity on stderr (default: info; debug "
                                                               "also prints tracebacks)")
    other.add_argument("--status-interval-s", type=float, metavar="S",
                       help="status line period (default: 0.5 s live line on a terminal, 5 s plain lines otherwise)")
    other.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    return p
