"""The `edi-live` command line: flags (and --config TOML) -> NodeConfig -> a source -> Node.run().

Owns: the flag definitions and help text, logging set-up, resolving `--usb-backend MODULE:CALLABLE`, signal
handling (SIGINT/SIGTERM stop the node cleanly, also during start-up; repeated ones are ignored while the stop
finishes), the summary, and mapping errors to exit codes: 0 success (also after Ctrl-C/SIGTERM), 2 usage error,
1 runtime error; every error is one line
`edi-live: error: ...` (a traceback only with --log-level debug).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import logging
import stat
import sys
import traceback
import warnings
from pathlib import Path
from typing import Any, Sequence

from edi_live import __version__
from edi_live.config import DEFAULT_ENDPOINT, LOG_LEVELS, NodeConfig, merge_options, read_toml
from edi_live.errors import ConfigError, EdiLiveError, RecordingError, SourceError
from edi_live.stop_signals import StopSignals

PROG = "edi-live"
log = logging.getLogger("edi_live")

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
  python -m tools.viewer        then open http://127.0.0.1:8080 in a browser (live frames and counters)
  python -m edi_live.client      prints what arrives (any program can subscribe: see edi_live/client.py)
  --dv-output tcp://HOST:PORT    DV's GUI (network input module) or dv-processing's NetworkReader shows them
  --out FILE.aedat4              opens in DV (file input), dv-processing, or --replay; one 8-bit frame each

Ctrl-C or SIGTERM stops cleanly (files finalised, exit 0; a second Ctrl-C is ignored while it stops). Exit codes: 0 ok, 1 runtime error, 2 usage error.
Every flag can also be set in --config FILE.toml with the same name (e.g. `every = 1000`, `c-on = 0.2`).
"""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse would print the usage block too)
        raise ConfigError(f"{message} (see {PROG} --help)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, argument_default=argparse.SUPPRESS, formatter_class=argparse.RawDescriptionHelpFormatter,
                description="Real-time EDI deblurring for DAVIS event cameras: one blurry APS frame plus its events "
                            "become sharp video, streamed over ZeroMQ.",
                epilog=EXAMPLES)
    src = p.add_argument_group("input (one of)")
    src.add_argument("--device", choices=("davis240", "davis346", "auto"),
                     help="a live DAVIS camera over USB ('auto': the first one found)")
    src.add_argument("--replay", metavar="FILE.aedat4", help="replay an AEDAT4 recording as if a camera were attached")
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
    dev.add_argument("--emulate-from", metavar="FILE.aedat4",
                     help="with --usb-backend drivers.emulator:backend: the recording the emulated camera streams")
    pace = p.add_argument_group("pacing")
    pace.add_argument("--speed", type=float, metavar="X",
                      help="replay speed: 1 = real time (default), 4 = 4x faster, 0 = as fast as possible")
    pace.add_argument("--loop", action="store_true", help="restart the replay at its end (time keeps increasing)")
    pace.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds (default: run "
                                                                         "until the input ends or Ctrl-C)")
    edi = p.add_argument_group("EDI reconstruction")
    edi.add_argument("--every", type=int, metavar="N", help="emit a latent frame every N events (default: 1000)")
    edi.add_argument("--c", type=float, metavar="C", help="fixed contrast threshold for both polarities "
                                                          "(default: estimated, re-estimated when it stops fitting)")
    edi.add_argument("--c-on", type=float, metavar="C", help="fixed ON threshold (with --c-off)")
    edi.add_argument("--c-off", type=float, metavar="C", help="fixed OFF threshold (with --c-on)")
    edi.add_argument("--mode", choices=("causal", "nearest", "fused"),
                     help="causal (default): latent frames from the latest deblurred APS frame, lowest latency; "
                          "nearest: wait for the next APS frame when it is nearer (adds latency, reported); "
                          "fused: every latent frame from both APS frames around it, best quality (waits for "
                          "the next APS frame: up to one frame interval, reported)")
    edi.add_argument("--max-fps", type=float, metavar="FPS", help="cap on latent frames per second (default: none)")
    edi.add_argument("--heartbeat-s", type=float, metavar="S",
                     help="keyframe interval on a static scene, seconds (default: 1.0)")
    edi.add_argument("--deblur-thread", action=argparse.BooleanOptionalAction,
                     help="causal mode: deblur APS frames on a helper thread so latent frames are not held up "
                          "(default: on, except for --speed 0 replays where throughput matters)")
    edi.add_argument("--reestimate-every", type=int, metavar="K",
                     help="also re-estimate c every K APS frames (default: 0 = only when it stops fitting)")
    edi.add_argument("--black-level", type=float, metavar="DN",
                     help="APS black level in 8-bit DN, taken off every APS frame so that the output is linear in "
                          "intensity (default: 0, right for DV's frames)")
    edi.add_argument("--quality-every", type=int, metavar="N",
                     help="score how well the output predicted one APS frame in N (the live quality figure; "
                          "default: 2, 0 = off)")
    out = p.add_argument_group("output")
    out.add_argument("--publish", action="append", metavar="ENDPOINT",
                     help=f"ZeroMQ PUB endpoint, repeatable (default: {DEFAULT_ENDPOINT}; loopback only)")
    out.add_argument("--no-publish", action="store_true", help="do not publish (e.g. only write --out)")
    out.add_argument("--curve-secret-key", metavar="FILE",
                     help="encrypt with CURVE using this server secret key file "
                          "(make one: python -m edi_live.publisher --gen-curve-keys DIR)")
    out.add_argument("--stats-interval-s", type=float, metavar="S",
                     help="period of the [b\"stats\", map] message on the socket, seconds (default: 1.0)")
    out.add_argument("--dv-output", metavar="tcp://HOST:PORT",
                     help="also serve the sharp frames as a DV network stream (AEDAT4 over TCP, as DV's network TCP "
                          "server output and dv-processing's NetworkWriter; loopback unless you choose otherwise)")
    out.add_argument("--dv-output-events", metavar="tcp://HOST:PORT",
                     help="also serve the input events, passed through, as a second DV network stream")
    out.add_argument("--out", metavar="FILE.aedat4", help="also write every emitted frame (8-bit gray, lossless)")
    out.add_argument("--record", metavar="FILE.aedat4", help="record the raw input as received, for --replay")
    adv = p.add_argument_group("advanced")
    adv.add_argument("--ring-events", type=int, metavar="N",
                     help="ring capacity in events, half kept as exposure history (default: 4194304 = 64 MiB)")
    adv.add_argument("--ring-frames", type=int, metavar="N", help="APS frames the ring holds (default: 16)")
    adv.add_argument("--ring-policy", choices=("drop_oldest", "wait"),
                     help="overflow policy (default: wait for replay/emulation, drop_oldest for a live camera)")
    other = p.add_argument_group("other")
    other.add_argument("--config", metavar="FILE.toml", help="read options from a TOML file; flags override it")
    other.add_argument("--log-level", choices=LOG_LEVELS, help="log verbosity on stderr (default: info; debug "
                                                               "also prints tracebacks)")
    other.add_argument("--status-interval-s", type=float, metavar="S",
                       help="status line period (default: 0.5 s live line on a terminal, 5 s plain lines otherwise)")
    other.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    return p


def options_from_args(argv: Sequence[str] | None) -> tuple[dict[str, Any], Path | None]:
    """Explicitly given flags (flag name -> value) and the --config path."""
    args = vars(build_parser().parse_args(argv))
    config_path = args.pop("config", None)
    return args, (Path(config_path) if config_path else None)


def build_config(flags: dict[str, Any], config_path: Path | None) -> NodeConfig:
    file_options = read_toml(config_path) if config_path is not None else {}
    options = merge_options(file_options, flags)
    options.pop("list_devices", None)
    config = NodeConfig.from_options(options)
    if config.source.device is None and config.source.replay is None and not config.source.dv_input:
        raise ConfigError(f"choose an input: --device davis240|davis346|auto, --replay FILE.aedat4 or --dv-input "
                          f"tcp://HOST:PORT "
                          f"(see {PROG} --help)")
    return config


def load_usb_backend(spec: str, **kwargs: Any) -> Any:
    """Import MODULE, call CALLABLE(**kwargs): a pyusb IBackend (a public hook for emulators and others).

    Keyword arguments the factory does not declare are left out, so any factory callable with no arguments
    works; ours (drivers.emulator:backend) also takes `model`, `recording`, `speed` and `loop`.
    """
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"--usb-backend {spec}: cannot import module {module_name!r} ({exc})") from exc
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ConfigError(f"--usb-backend {spec}: module {module_name!r} has no callable {attr!r}")
    kwargs = _accepted_kwargs(factory, kwargs)
    try:
        backend = factory(**kwargs)
    except EdiLiveError:
        raise
    except Exception as exc:
        raise SourceError(f"--usb-backend {spec} failed to create a backend: {type(exc).__name__}: {exc}") from exc
    if not callable(getattr(backend, "enumerate_devices", None)):  # what usb.core.find calls first
        raise ConfigError(f"--usb-backend {spec}: {attr}() returned a {type(backend).__name__}, not a pyusb "
                          f"backend (usb.backend.IBackend)")
    return backend


def _accepted_kwargs(factory: Any, kwargs: dict[str, Any]) -> dict[str, Any]:
    """The part of `kwargs` that `factory` declares (all of it if it takes **kwargs or has no signature)."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return kwargs
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return kwargs
    names = {p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                  inspect.Parameter.KEYWORD_ONLY)}
    return {k: v for k, v in kwargs.items() if k in names}


def _existing_file(path: Path, flag: str) -> None:
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise RecordingError(f"no such file (check the {flag} path)", str(path)) from None
    except OSError as exc:
        raise RecordingError(f"cannot open the recording ({exc.strerror or exc})", str(path)) from None
    if stat.S_ISDIR(mode):
        raise RecordingError(f"is a directory, not a recording (give {flag} an .aedat4 file)", str(path))
    if not stat.S_ISREG(mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
        raise RecordingError(f"is {kind}, not a regular file: {flag} seeks in the recording, so save the stream "
                             f"to an .aedat4 file first", str(path))


def make_source(config: NodeConfig, explicit: set[str] | frozenset = frozenset()) -> Any:
    """The driver for the configured input (not yet opened)."""
    import drivers

    s = config.source
    if s.dv_input:
        return drivers.open_source("dv", endpoints=list(s.dv_input), reconnect=s.reconnect)
    if s.replay is not None:
        _existing_file(Path(s.replay), "--replay")
        return drivers.open_source("replay", path=str(s.replay), speed=s.speed, loop=s.loop, decode_process=True)
    backend = None
    if s.usb_backend is not None:
        kwargs: dict[str, Any] = {}
        if s.device != "auto":  # an emulated camera presents the model asked for (not the file's, not its default)
            kwargs["model"] = s.device
        if s.emulate_from is not None:
            _existing_file(Path(s.emulate_from), "--emulate-from")
            kwargs["recording"] = str(s.emulate_from)
            if "speed" in explicit:
                kwargs["speed"] = s.speed
            if s.loop:
                kwargs["loop"] = True
        backend = load_usb_backend(s.usb_backend, **kwargs)
    return drivers.open_source(s.device, serial=s.serial, backend=backend, exposure_us=s.exposure_us,
                               frame_interval_us=s.frame_interval_us, reconnect=s.reconnect,
                               policy=config.ring_policy)


def list_devices_command(flags: dict[str, Any]) -> int:
    import drivers

    backend = load_usb_backend(flags["usb_backend"]) if flags.get("usb_backend") else None
    devices = drivers.list_devices(backend)
    if not devices:
        print("no DAVIS camera found (is it plugged in? on Linux, is the udev rule installed?)")
    for d in devices:
        print(d)
    return 0


class _LogHandler(logging.StreamHandler):
    """stderr logging that first erases the live status line on a terminal (it is redrawn at the next tick);
    without this a log message is glued to the end of the status line."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        isatty = getattr(self.stream, "isatty", None)
        return "\r\x1b[K" + text if isatty is not None and isatty() else text


_DEVICE_ONLY = ("serial", "exposure_us", "frame_interval_us", "usb_backend")


def _warn_ignored(config: NodeConfig, explicit: set[str]) -> None:
    """Options that do nothing for the chosen input are said aloud rather than silently dropped."""
    s = config.source
    if s.replay is not None:
        given = [name for name in _DEVICE_ONLY if getattr(s, name) is not None] + (["reconnect"] if s.reconnect
                                                                                     else [])
        if given:
            log.warning("ignored with --replay (camera options): %s",
                        ", ".join("--" + name.replace("_", "-") for name in given))
    elif s.emulate_from is None and "speed" in explicit:
        log.warning("ignored with a live camera: --speed (it paces --replay and --emulate-from only)")


_LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]", "::1")


def _warn_if_exposed(config: NodeConfig) -> None:
    """Loopback is the default; a network endpoint without CURVE is allowed (an explicit choice) but said aloud."""
    for endpoint in (config.output.dv_output, config.output.dv_output_events):
        host = (endpoint or "").partition("://")[2].rsplit(":", 1)[0]
        if endpoint and host not in _LOOPBACK_HOSTS:
            log.warning("serving DV on %s: anyone who can reach this machine can connect (the DV protocol has no "
                        "encryption here; use a 127.0.0.1 endpoint unless you mean it)", endpoint)
    if config.publisher.curve_secret_key is not None:
        return
    for endpoint in config.publisher.endpoints:
        scheme, _, rest = endpoint.partition("://")
        host = rest.rsplit(":", 1)[0] if scheme == "tcp" else ""
        if scheme in ("tcp", "udp", "pgm", "epgm") and host not in _LOOPBACK_HOSTS:
            log.warning("publishing on %s without encryption: anyone who can reach this machine can subscribe "
                        "(use --curve-secret-key FILE, or a 127.0.0.1 endpoint)", endpoint)


def _log_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None,
                 line: str | None = None) -> None:
    """Python warnings (from a library, or a driver's notice) as edi-live log lines, not raw RuntimeWarnings."""
    log.warning("%s", message)


def _setup_logging(level: str, stream: Any = None) -> None:
    warnings.showwarning = _log_warning
    handler = _LogHandler(sys.stderr if stream is None else stream)
    handler.setFormatter(logging.Formatter("edi-live: %(levelname)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    wanted = getattr(logging, level.upper())
    root.setLevel(max(wanted, logging.WARNING))  # third-party debug chatter (numba) stays out
    for name in ("edi_live", "drivers"):
        logging.getLogger(name).setLevel(wanted)


def _error_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{PROG}: error: {text}"


def main(argv: Sequence[str] | None = None) -> int:
    """The program (argv None: sys.argv) or an in-process call. SIGINT/SIGTERM are handled from the start; an
    in-process call restores the previous handlers on return. The program, once stopped by a signal, ignores
    further ones until it has exited: Python resets its own handlers to the default action while it finalises
    (e.g. while the replay's decoding child is reaped), where a late Ctrl-C would kill it (rc -2)."""
    signals = StopSignals()
    signals.install()
    try:
        return _main(argv, signals)
    finally:
        if argv is None and signals.received is not None:
            signals.ignore_from_now_on()
        else:
            signals.restore()


def _main(argv: Sequence[str] | None, signals: StopSignals) -> int:
    level = "info"
    try:
        flags, config_path = options_from_args(argv)
        level = flags.get("log_level", "info")
        _setup_logging(level)
        if flags.pop("list_devices", False):
            return list_devices_command(flags)
        config = build_config(flags, config_path)
        level = config.log_level
        _setup_logging(level)
        _warn_if_exposed(config)
        _warn_ignored(config, set(flags))
        source = make_source(config, explicit=set(flags))
        from edi_live.node import Node

        node = Node(config, source, status_stream=sys.stderr)
        signals.attach(node)
        try:
            node.run()
        finally:
            if node.final_stats and node.started.is_set():  # no summary when it never got going
                from edi_live.stats import format_summary

                print(format_summary(node.final_stats, node.elapsed_s), file=sys.stderr)
        return 0
    except SystemExit as exc:  # --help / --version
        return int(exc.code or 0)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except EdiLiveError as exc:
        if level == "debug":
            traceback.print_exc()
        print(_error_line(exc), file=sys.stderr)
        return exc.exit_code
    except Exception as exc:  # a bug: still one line, the traceback at --log-level debug
        if level == "debug":
            traceback.print_exc()
        print(_error_line(f"internal error: {type(exc).__name__}: {exc} (rerun with --log-level debug for the "
                          f"traceback and report it)"), file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
