"""Watch an edi-live stream: terminal rates, a live MJPEG page for any browser, and MP4 or PNG recording.

Headless OpenCV (the wheel edi-live depends on) cannot open windows, so the live view is a web page served
by this process (http://127.0.0.1:8080 by default, loopback only). It subscribes with `edi_live.client`,
skipping to the newest frame when it falls behind (use --all to receive every frame, e.g. for recording).

This module owns the receive loop (Viewer), the status line and the command line; the live page is
tools/viewer_http.py, the MP4 and PNG files tools/viewer_output.py.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from edi_live import live_line
from edi_live.checks import finite_number
from edi_live.client import DEFAULT_ENDPOINT, ClientHandshakeError, Subscriber, number_arg
from edi_live.errors import ClientError, EdiLiveError
from tools.viewer_http import BOUNDARY, FrameHub, MjpegServer, json_safe  # noqa: F401 - BOUNDARY, json_safe: API
from tools.viewer_output import MP4_SUFFIXES, Recorder, to_u8  # noqa: F401 - the module's API, as before

log = logging.getLogger("edi-live-viewer")

EPILOG = """examples:
  python -m tools.viewer                              # then open http://127.0.0.1:8080
  python -m tools.viewer --mp4 sharp.mp4 --all --no-http --duration 10
  python -m tools.viewer --endpoint tcp://10.0.0.5:5555 --png frames/ --http 127.0.0.1:9000
  python -m tools.viewer --curve-server-key keys/server.key   # edi-live ran with --curve-secret-key

status line: recv = frames/s this viewer got; node = frames/s, events/s and c from the node's stats message;
latency = node-side p50/p99 from event arrival to frame sent; node drops = data the node dropped anywhere
(source, ring, publisher); lost = gaps in seq (frames this viewer never received); skipped = frames drained
unshown because the viewer fell behind (newest-only mode).
"""


class Rates:
    """Frames per second received and frames lost (gaps in seq) as seen by this viewer."""

    def __init__(self) -> None:
        self.frames = 0
        self.lost = 0
        self.last_seq: int | None = None
        self._window_start = time.monotonic()
        self._window_frames = 0
        self.fps = 0.0

    def add(self, seq: int, skipped: int = 0) -> None:
        """Count one shown frame; `skipped` frames were received but drained unshown just before it."""
        if self.last_seq is not None and seq > self.last_seq + 1:
            self.lost += max(0, seq - self.last_seq - 1 - skipped)
        self.last_seq = seq
        self.frames += 1
        self._window_frames += 1

    def tick(self) -> bool:
        """Update fps once a second; True when it did."""
        elapsed = time.monotonic() - self._window_start
        if elapsed < 1.0:
            return False
        self.fps = self._window_frames / elapsed
        self._window_start, self._window_frames = time.monotonic(), 0
        return True


def _num(stats: dict, key: str, scale: float = 1.0, fmt: str = "{:.2f}") -> str:
    value = stats.get(key)
    return fmt.format(value * scale) if finite_number(value) else "-"  # (a publisher may send NaN, inf or true)


STATS_STALE_S = 3.0  # the node sends stats once a second: older ones describe a node that stopped or went away


_SEP = " | "


def status_line(rates: Rates, skipped: int, stats: dict | None, stats_age_s: float = 0.0) -> str:
    parts = [f"recv {rates.fps:6.1f} fps"]
    if stats and stats_age_s > STATS_STALE_S:
        parts.append(f"no stats from the node for {stats_age_s:.0f} s (stopped, or unreachable?)")
    elif stats:
        on, off = stats.get("c_on"), stats.get("c_off")
        # unequal thresholds are shown as such (the stats' `c` is then only their mean)
        split = "c_on" in stats and "c_off" in stats and on != off
        c = f"{_num(stats, 'c_on')}/{_num(stats, 'c_off')}" if split or "c" not in stats else _num(stats, "c")
        parts.append(f"node {_num(stats, 'frames_per_s', fmt='{:.1f}')} fps, "
                     f"{_num(stats, 'events_per_s', 1e-6)} Mev/s, c {c}")
        parts.append(f"latency p50 {_num(stats, 'latency_p50_us', 1e-3)} ms p99 "
                     f"{_num(stats, 'latency_p99_us', 1e-3)} ms")
        # all of the node's drops (source, ring, publisher), not only the publisher's
        drops_key = "drops" if "drops" in stats else "publish_dropped"
        parts.append(f"node drops {_num(stats, drops_key, fmt='{:.0f}')}")
        if finite_number(stats.get("pred_psnr_db")):  # the live quality figure (docs/quality.md)
            parts.append(f"predicts next APS frame {_num(stats, 'pred_psnr_db', fmt='{:.1f}')} dB "
                         f"(nothing moved: {_num(stats, 'still_psnr_db', fmt='{:.1f}')} dB)")
    else:
        parts.append("no stats yet")
    parts.append(f"lost {rates.lost}, skipped {skipped}")
    return _SEP.join(parts)


def parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with PORT 0-65535, e.g. 127.0.0.1:8080 (got {text!r})")
    return host, int(port)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tools.viewer", description=__doc__.split("\n\n")[0],
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = parser.add_argument_group("input")
    src.add_argument("--endpoint", default=DEFAULT_ENDPOINT,
                     help=f"edi-live publisher to subscribe to (default {DEFAULT_ENDPOINT})")
    src.add_argument("--curve-server-key", metavar="FILE",
                     help="the publisher's CURVE public key file (server.key) when it encrypts")
    src.add_argument("--all", action="store_true",
                     help="receive every frame instead of skipping to the newest (for lossless recording)")
    out = parser.add_argument_group("output")
    out.add_argument("--http", type=parse_host_port, default=("127.0.0.1", 8080), metavar="HOST:PORT",
                     help="serve the live MJPEG page here (default 127.0.0.1:8080; port 0 = any free port)")
    out.add_argument("--no-http", action="store_true", help="do not serve the live page")
    out.add_argument("--mp4", type=Path, metavar="FILE", help="also write an MP4 (mp4v codec)")
    out.add_argument("--mp4-fps", type=number_arg(float, 0.1, finite=True), default=30.0, metavar="FPS",
                     help="frame rate stored in the MP4 (default 30)")
    out.add_argument("--png", type=Path, metavar="DIR", help="also write every shown frame as DIR/frame_SEQ.png")
    out.add_argument("--jpeg-quality", type=number_arg(int, 1, 100, finite=True), default=85, metavar="Q",
                     help="MJPEG quality 1-100 (default 85)")
    run = parser.add_argument_group("run")
    run.add_argument("--duration", type=number_arg(float, 0.001, finite=True), metavar="SECONDS",
                     help="stop after this long (default: Ctrl-C)")
    run.add_argument("--max-frames", type=number_arg(int, 1, finite=True), metavar="N", help="stop after N frames")
    run.add_argument("--quiet", action="store_true", help="no status line")
    return parser


_BAD_SHOWN = 10  # bad messages logged one by one; a foreign publisher would otherwise write a line per message


class Viewer:
    """The receive loop with its outputs; `run()` until stopped, `close()` finalizes files and sockets."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.stop = threading.Event()
        self.hub = FrameHub(args.jpeg_quality)
        self.rates = Rates()
        self.bad_messages = 0
        self.recorder = Recorder(args.mp4, args.png, args.mp4_fps)
        self.server = None if args.no_http else MjpegServer(self.hub, *args.http)
        self.sub = Subscriber(args.endpoint, newest_only=not args.all, curve_server_key=args.curve_server_key)
        self._tty = sys.stderr.isatty()
        self._stats_at = time.monotonic()  # when the newest stats message came
        self._skipped_shown = 0  # self.sub.skipped when the latest frame was shown
        self._drawn: str | None = None  # the status line last drawn on the terminal

    @property
    def url(self) -> str | None:
        return self.server.url if self.server else None

    def run(self) -> None:
        if self.server:
            self.server.start()
            log.info("live page: %s", self.server.url)
            if self.args.http[0] not in ("127.0.0.1", "localhost", "::1"):
                log.warning("the live page is reachable from other machines (--http %s)", self.args.http[0])
        deadline = None if self.args.duration is None else time.monotonic() + self.args.duration
        while not self.stop.is_set():
            if deadline is not None and time.monotonic() >= deadline:
                break
            if self.args.max_frames is not None and self.rates.frames >= self.args.max_frames:
                break
            self._step()

    def _step(self) -> None:
        try:
            item = self.sub.recv(0.1)
        except ClientHandshakeError:
            raise  # no frame will ever come: the run ends with this one line
        except ClientError as exc:
            self._bad(exc)
            item = None
        try:  # apart from the frame: a bad stats message must not cost the frame read with it
            if self.sub.recv_stats(0) is not None:
                self._stats_at = time.monotonic()
        except ClientHandshakeError:
            raise
        except ClientError as exc:
            self._bad(exc)
        if item is not None:
            header, image = item
            # every skip since the last frame shown, also those of a step that ended in a bad message
            self.rates.add(header["seq"], self.sub.skipped - self._skipped_shown)
            self._skipped_shown = self.sub.skipped
            self.hub.put(image)
            self.recorder.write(header, image)
        if self.rates.tick():
            line = status_line(self.rates, self.sub.skipped, self.sub.last_stats,
                               time.monotonic() - self._stats_at)
            self.hub.status = {"viewer_fps": round(self.rates.fps, 1), "lost": self.rates.lost,
                               "skipped": self.sub.skipped, "line": line, "node": self.sub.last_stats}
            if not self.args.quiet:
                try:  # on a terminal: redrawn in place, in rows that fit it (a wrapped line left a row per redraw)
                    sys.stderr.write(live_line.redraw(line, live_line.columns(sys.stderr), _SEP) if self._tty
                                     else line + "\n")
                    sys.stderr.flush()
                    self._drawn = line
                except (OSError, ValueError):  # stderr went away ('2>&1 | head'): the status ends, not the run
                    self.args.quiet = True

    def _bad(self, exc: ClientError) -> None:
        self.bad_messages += 1
        if self.bad_messages <= _BAD_SHOWN:
            more = "; further bad messages are counted in the summary only" if self.bad_messages == _BAD_SHOWN else ""
            log.warning("ignored a bad message: %s%s", exc, more)

    def close(self) -> None:
        self.hub.close()
        self.recorder.close()
        if self.server:
            self.server.close()
        self.sub.close()
        if self._tty and not self.args.quiet:
            try:
                sys.stderr.write(live_line.end(self._drawn, live_line.columns(sys.stderr), _SEP))
            except (OSError, ValueError):
                pass
        saved = f", {self.recorder.written} saved" if (self.args.mp4 or self.args.png) else ""
        if self.recorder.skipped_size:
            saved += f" ({self.recorder.skipped_size} left out of the MP4: another size than its first frame)"
        log.info("received %d frames (lost %d, skipped %d, bad %d)%s", self.rates.frames, self.rates.lost,
                 self.sub.skipped, self.bad_messages, saved)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # (on a terminal a message first erases the status line, which waits at its start between redraws)
    logging.basicConfig(level=logging.INFO, format="viewer: %(message)s", handlers=[live_line.LogHandler()])
    try:
        viewer = Viewer(args)
    except EdiLiveError as exc:
        print(f"viewer: error: {exc}", file=sys.stderr)
        return 1
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: viewer.stop.set())
        signal.signal(signal.SIGINT, lambda *_: viewer.stop.set())
        # a closed terminal or ssh session: its default action killed us with the MP4 unreadable (no moov atom)
        if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) != signal.SIG_IGN:  # (nohup: ignored)
            signal.signal(signal.SIGHUP, lambda *_: viewer.stop.set())
    try:
        viewer.run()
    except EdiLiveError as exc:
        print(f"viewer: error: {exc}", file=sys.stderr)
        return 1
    finally:
        viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
