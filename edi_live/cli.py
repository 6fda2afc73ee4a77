"""The `edi-live` command line: flags (and --config TOML) -> NodeConfig -> a source -> Node.run().

Owns (the flags and their help are in cli_parser.py): logging set-up, resolving `--usb-backend MODULE:CALLABLE`, signal
handling (SIGINT/SIGTERM stop the node cleanly, also during start-up; repeated ones are ignored while the stop
finishes), the summary, and mapping errors to exit codes: 0 success (also after Ctrl-C/SIGTERM), 2 usage error,
1 runtime error; every error is one line
`edi-live: error: ...` (a traceback only with --log-level debug).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import logging
import stat
import sys
import traceback
import warnings
from pathlib import Path
from typing import Any, Sequence

from edi_live.cli_parser import PROG, build_parser
from edi_live.config import NodeConfig, merge_options, read_toml
from edi_live.console import escape_what_cannot_be_encoded, occupy_closed_standard_fds, print_lines
from edi_live.file_roles import check_apart
from edi_live.live_line import LogHandler
from edi_live.resource_limits import check_open_files, out_of_memory
from edi_live.datatypes import SourceInfo
from edi_live.errors import ConfigError, EdiLiveError, RecordingError, SourceError
from edi_live.stop_signals import StopRequested, StopSignals

log = logging.getLogger("edi_live")

def options_from_args(argv: Sequence[str] | None) -> tuple[dict[str, Any], Path | None]:
    """Explicitly given flags (flag name -> value) and the --config path."""
    args = vars(build_parser().parse_args(argv))
    config_path = args.pop("config", None)
    if config_path == "":  # (an unset shell variable) read as no config, the run went on without the options meant
        raise ConfigError("config: expected a file path, not an empty one (got '')")
    return args, (Path(config_path) if config_path is not None else None)


def build_config(flags: dict[str, Any], config_path: Path | None) -> NodeConfig:
    file_options = read_toml(config_path) if config_path is not None else {}
    options = merge_options(file_options, flags)
    options.pop("list_devices", None)
    config = NodeConfig.from_options(options)
    check_apart({"config": config_path}, {"out": config.output.out, "record": config.output.record,
                                          "save-calibration": config.save_calibration})
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
    if not module_name or not attr:
        raise ConfigError(f"--usb-backend {spec}: expected MODULE:CALLABLE, e.g. drivers.emulator:backend")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"--usb-backend {spec}: cannot import module {module_name!r} ({exc})") from exc
    except Exception as exc:  # the module's own fault (a typo, an error at import): not edi-live's bug
        raise ConfigError(f"--usb-backend {spec}: importing module {module_name!r} failed "
                          f"({type(exc).__name__}: {exc})") from exc
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


def colour_line(info: SourceInfo, pattern: str | None = None, seen: str | None = None) -> str | None:
    """The summary's line for a colour camera (None for a mono one); `pattern`: --bayer-pattern's, if given;
    `seen`: the pattern the reconstructor ran on (final stats' bayer_pattern), for a source that named none but
    sent BGR frames (DV's demosaiced recordings)."""
    used = pattern or info.color_filter or seen
    if used is None:
        return None
    how = (" given by --bayer-pattern" if pattern else "" if info.color_filter
           else ", the source's BGR frames re-mosaiced")
    return f"  camera: {info.label} {info.width}x{info.height}, colour ({used} Bayer mosaic{how})"


def list_devices_command(flags: dict[str, Any]) -> int:
    import drivers

    ignored = sorted(f"--{name.replace('_', '-')}" for name in set(flags) - {"usb_backend", "log_level"})
    if ignored:  # e.g. --calibrate-dark: not done, so say so
        log.warning("ignored with --list-devices: %s (it only lists the cameras and exits)", ", ".join(ignored))
    backend = load_usb_backend(flags["usb_backend"]) if flags.get("usb_backend") else None
    devices = drivers.list_devices(backend)
    print_lines([str(d) for d in devices] or
                ["no DAVIS camera found (is it plugged in? on Linux, is the udev rule installed?)"])
    return 0


def calibrate_dark_command(config: NodeConfig, source: Any, n_frames: int, signals: StopSignals) -> int:
    """--calibrate-dark N: the black level of N dark frames, written into the calibration file (one line out)."""
    from edi_live.dark_calibration import calibrate_dark

    result, target = calibrate_dark(source, n_frames, config.save_calibration, signals)
    _say(f"{PROG}: black level {result.black_level:g} DN (noise {result.noise_dn:g} DN, {result.frames} dark "
         f"frames of {source.info.label}) written to {target}")
    return 0


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
    if config.publisher.curve_secret_key is not None and not config.publisher.endpoints:
        log.warning("ignored with --no-publish: --curve-secret-key (it encrypts the published frames)")
    if config.edi.reestimate_every and (config.edi.c is not None or config.edi.c_on is not None):
        log.warning("ignored with a fixed c: --reestimate-every (c is never estimated)")
    if config.edi.latent_denoise and config.edi.mode != "causal":
        log.warning("ignored with --mode %s: --latent-denoise (it filters causal latent frames only)", config.edi.mode)


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
    handler = LogHandler(sys.stderr if stream is None else stream)
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


def _say(text: str) -> None:
    """One message on stderr; a stderr that went away ('2>&1 | head') does not turn a finished run into an error,
    and a closed one ('2>&-': sys.stderr is None, where print() would fall back to stdout) takes nothing."""
    if sys.stderr is None:
        return
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """The program (argv None: sys.argv) or an in-process call. SIGINT/SIGTERM are handled from the start; an
    in-process call restores the previous handlers on return. The program, once stopped by a signal, ignores
    further ones until it has exited: Python resets its own handlers to the default action while it finalises
    (e.g. while the replay's decoding child is reaped), where a late Ctrl-C would kill it (rc -2)."""
    occupy_closed_standard_fds()  # first: before any file of ours could take a closed stdin/stdout/stderr's number
    signals = StopSignals()
    signals.install()
    escape_what_cannot_be_encoded()
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
        dark_frames = flags.pop("calibrate_dark", None)
        with signals.raising():  # reading a config FIFO may wait: a stop signal ends it (nothing has started)
            config = build_config(flags, config_path)
        level = config.log_level
        _setup_logging(level)
        _warn_if_exposed(config)
        serves = config.publisher.enabled or config.output.dv_output or config.output.dv_output_events
        if serves and dark_frames is None:  # (--calibrate-dark only measures)
            check_open_files()
        _warn_ignored(config, set(flags))
        outputs = [f"--{name.replace('_', '-')}" for name in ("out", "record", "dv_output", "dv_output_events")
                   if getattr(config.output, name) is not None]
        if dark_frames is not None and outputs:  # it measures and exits: nothing is reconstructed or recorded
            log.warning("ignored with --calibrate-dark: %s (it only measures the black level)", ", ".join(outputs))
        if dark_frames is not None and config.source.loop:  # a recording without frames would loop for ever
            log.warning("--loop is ignored with --calibrate-dark: each recorded frame is measured once")
            config = dataclasses.replace(config, source=dataclasses.replace(config.source, loop=False))
        source = make_source(config, explicit=set(flags))
        if dark_frames is not None:
            return calibrate_dark_command(config, source, dark_frames, signals)
        from edi_live.node import Node

        node = Node(config, source, status_stream=sys.stderr)
        signals.attach(node)
        try:
            node.run(warming_up=signals.raising)  # a stop signal ends a cold kernel compile at once
        finally:
            if node.final_stats and node.started.is_set():  # no summary when it never got going
                from edi_live.stats import format_summary

                _say(format_summary(node.final_stats, node.elapsed_s))
                line = colour_line(source.info, config.edi.color_filter, node.final_stats.get("bayer_pattern"))
                if line is not None:
                    _say(line)
                if line is not None and not (source.info.is_color or config.edi.color_filter) \
                        and config.edi.latent_denoise and config.edi.mode == "causal":  # (no start-up warning)
                    _say("  --latent-denoise was ignored: the source's frames were colour (BGR)")
        return 0
    except SystemExit as exc:  # --help / --version
        return int(exc.code or 0)
    except StopRequested:  # already logged by the handler
        return 0
    except KeyboardInterrupt:
        _say(f"{PROG}: interrupted")
        return 130
    except EdiLiveError as exc:
        if level == "debug":
            traceback.print_exc()
        exc = out_of_memory(exc) or exc
        _say(_error_line(exc))
        return exc.exit_code
    except Exception as exc:  # a bug: still one line, the traceback at --log-level debug
        if level == "debug":
            traceback.print_exc()
        if (short := out_of_memory(exc)) is not None:
            _say(_error_line(short))
            return short.exit_code
        _say(_error_line(f"internal error: {type(exc).__name__}: {exc} (rerun with --log-level debug for the "
                         f"traceback and report it)"))
        return 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
