"""Watch an edi-live stream: terminal rates, a live MJPEG page for any browser, and MP4 or PNG recording.

Headless OpenCV (the wheel edi-live depends on) cannot open windows, so the live view is a web page served
by this process (http://127.0.0.1:8080 by default, loopback only). It subscribes with `edi_live.client`,
skipping to the newest frame when it falls behind (use --all to receive every frame, e.g. for recording).
"""

from __future__ import annotations

import argparse
import html
import http.server
import itertools
import json
import math
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edi_live.client import DEFAULT_ENDPOINT, ClientHandshakeError, Subscriber
from edi_live.errors import ClientError, EdiLiveError

log = logging.getLogger("edi-live-viewer")
BOUNDARY = "edi-live-frame"
MP4_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv")
"""Names OpenCV writes an mp4v video under (.txt fails at the first frame, .png writes something else)."""

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


def to_u8(image: np.ndarray) -> np.ndarray:
    """Display-ready 8 bits, gray (h, w) or colour (h, w, 3) BGR as received: u2 keeps its top byte, floats are
    clipped to 0..255."""
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return np.clip(np.nan_to_num(image), 0, 255).astype(np.uint8)


class FrameHub:
    """The newest frame and stats, shared by the receive loop and the HTTP threads; JPEG encoded once per frame."""

    def __init__(self, jpeg_quality: int = 85) -> None:
        self._cond = threading.Condition()
        self._image: np.ndarray | None = None
        self._jpeg: bytes | None = None
        self.version = 0
        self.closed = False
        self.status: dict[str, Any] = {}
        self._quality = jpeg_quality

    def put(self, image: np.ndarray) -> None:
        with self._cond:
            self._image, self._jpeg = image, None
            self.version += 1
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def wait_jpeg(self, after_version: int, timeout_s: float) -> tuple[int, bytes | None]:
        """(version, jpeg) of a frame newer than after_version, or (after_version, None) on timeout/close."""
        with self._cond:
            self._cond.wait_for(lambda: self.version > after_version or self.closed, timeout_s)
            if self.version <= after_version or self._image is None:
                return after_version, None
            if self._jpeg is None:
                ok, buf = cv2.imencode(".jpg", to_u8(self._image), [cv2.IMWRITE_JPEG_QUALITY, self._quality])
                self._jpeg = buf.tobytes() if ok else None
            return self.version, self._jpeg


# The frame fills the window left of the counters, scaled with its aspect ratio kept (object-fit: contain) and
# with sharp pixels (a 346x260 sensor is small on a screen); on a portrait window the counters go below it.
PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>edi-live viewer</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
html,body{height:100%;margin:0;background:#000;color:#ccc;font:13px monospace}
#wrap{display:flex;height:100vh}
#view{flex:1;min-width:0;min-height:0}
#live{display:block;width:100%;height:100%;object-fit:contain;image-rendering:pixelated}
#side{flex:none;width:23em;overflow:auto;padding:0 8px;border-left:1px solid #333}
@media (max-aspect-ratio:1/1){#wrap{flex-direction:column}#side{width:auto;height:40vh;border:0}}
</style></head>
<body><div id="wrap"><div id="view"><img id="live" src="/stream.mjpg" alt="edi-live stream"></div>
<div id="side"><pre id="line">@LINE@</pre>
<details><summary>all counters</summary><pre id="status"></pre></details></div></div>
<script>
async function update() {
  try { const s = await (await fetch('/status.json')).json();
        document.getElementById('line').textContent = s.line.split(' | ').join('\n');
        document.getElementById('status').textContent = JSON.stringify(s.node, null, 1); } catch (e) {}
}
update(); setInterval(update, 1000);
</script></body></html>
"""


_JSON_DEPTH = 32  # msgpack decodes ~1000 levels of nesting, past Python's recursion limit in json.dumps


def json_safe(value: Any, depth: int = 0) -> Any:
    """A copy that strict JSON can carry: the node's stats map comes from the network and may hold binary
    values or keys, msgpack extension types, non-finite floats (bytes become hex, the rest their repr) or
    nesting deeper than _JSON_DEPTH levels (cut off there, with a string saying so)."""
    if isinstance(value, (dict, list, tuple)) and depth >= _JSON_DEPTH:
        return f"(nested deeper than {_JSON_DEPTH} levels)"
    if isinstance(value, dict):
        return {_json_key(k): json_safe(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, depth + 1) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    return repr(value)


def _json_key(key: Any) -> str:
    return key if isinstance(key, str) else bytes(key).hex() if isinstance(key, (bytes, bytearray)) else repr(key)


def make_handler(hub: FrameHub) -> type[http.server.BaseHTTPRequestHandler]:
    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.0"

        def log_message(self, fmt: str, *args: object) -> None:
            log.debug("http: " + fmt, *args)

        def _send(self, body: bytes, content_type: str, code: int = 200) -> None:
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            path = self.path.split("?")[0]
            if path in ("/", "/index.html"):
                line = str(hub.status.get("line", "waiting for stats...")).replace(" | ", "\n")
                self._send(PAGE.replace("@LINE@", html.escape(line)).encode(), "text/html; charset=utf-8")
            elif path == "/status.json":
                self._send(json.dumps(json_safe(hub.status)).encode(), "application/json")
            elif path == "/frame.jpg":
                _, jpeg = hub.wait_jpeg(hub.version - 1, 0)
                if jpeg is None:
                    self._send(b"no frame received yet\n", "text/plain", 503)
                else:
                    self._send(jpeg, "image/jpeg")
            elif path == "/stream.mjpg":
                self._stream()
            else:
                self._send(b"not found: try / or /stream.mjpg\n", "text/plain", 404)

        def _stream(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            version = max(0, hub.version - 1)  # start with the current frame if there is one
            try:
                while not hub.closed:
                    new_version, jpeg = hub.wait_jpeg(version, 1.0)
                    if jpeg is None:
                        continue
                    version = new_version
                    self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                                     f"Content-Length: {len(jpeg)}\r\n\r\n".encode() + jpeg + b"\r\n")
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError):
                pass  # the browser went away

    return Handler


class MjpegServer:
    """ThreadingHTTPServer on its own thread: / (page), /stream.mjpg, /frame.jpg, /status.json."""

    def __init__(self, hub: FrameHub, host: str, port: int) -> None:
        try:
            self._server = http.server.ThreadingHTTPServer((host, port), make_handler(hub))
        except OSError as exc:
            raise EdiLiveError(f"cannot serve the live page on http://{host}:{port}: {exc.strerror}; "
                               "choose another with --http HOST:PORT or use --no-http") from exc
        self._server.daemon_threads = True
        self.url = f"http://{host}:{self._server.server_address[1]}/"
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="viewer-http", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5)


class Recorder:
    """MP4 (mp4v) and/or PNG output. The MP4 size is fixed by the first frame; other sizes are skipped."""

    def __init__(self, mp4: Path | None, png_dir: Path | None, fps: float) -> None:
        self.mp4, self.png_dir, self.fps = mp4, png_dir, fps
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.written = 0
        self.skipped_size = 0
        self._png_renamed = False
        if png_dir is not None:
            try:
                png_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise EdiLiveError(f"cannot create the --png folder {png_dir}: {exc.strerror}") from exc
        if mp4 is not None:  # cv2 opens the file only at the first frame: check the place now, not minutes later
            folder = mp4.resolve().parent
            if mp4.is_dir() or not folder.is_dir() or not os.access(folder, os.W_OK):
                why = "is a directory" if mp4.is_dir() else f"folder {folder} is missing or not writable"
                raise EdiLiveError(f"cannot write --mp4 {mp4}: {why}")
            if mp4.suffix.lower() not in MP4_SUFFIXES:
                raise EdiLiveError(f"cannot write --mp4 {mp4}: the name must end in {', '.join(MP4_SUFFIXES)} "
                                   "(OpenCV picks the container by it)")

    def write(self, header: dict, image: np.ndarray) -> None:
        shown = to_u8(image)  # gray or BGR: PNG keeps either as it is, the MP4 is always BGR
        if self.png_dir is not None:
            self._write_png(header["seq"], shown)
        if self.mp4 is not None:
            size = (shown.shape[1], shown.shape[0])
            if self._writer is None:
                self._writer = cv2.VideoWriter(str(self.mp4), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, size)
                if not self._writer.isOpened():
                    raise EdiLiveError(f"cannot open {self.mp4} for MP4 (mp4v) writing")
                self._size = size
            if size != self._size:
                if not self.skipped_size:
                    log.warning("frame %s is %dx%d, the MP4 is %dx%d: frames of another size are left out of it "
                                "(counted in the summary)", header["seq"], *size, *self._size)
                self.skipped_size += 1
                return
            self._writer.write(shown if shown.ndim == 3 else cv2.cvtColor(shown, cv2.COLOR_GRAY2BGR))
        self.written += 1

    def _write_png(self, seq: int, shown: np.ndarray) -> None:
        """frame_SEQ.png, or frame_SEQ_2.png, _3, ... when that name is taken (an earlier recording in the folder,
        or a publisher restarted: its seq starts again): a saved frame is never overwritten."""
        ok, png = cv2.imencode(".png", shown)
        if not ok:
            raise EdiLiveError(f"cannot encode frame {seq} as PNG")
        for copy in itertools.count(1):
            path = self.png_dir / (f"frame_{seq:09d}.png" if copy == 1 else f"frame_{seq:09d}_{copy}.png")
            try:
                fh = open(path, "xb")
            except FileExistsError:
                if not self._png_renamed:
                    self._png_renamed = True
                    log.warning("%s exists (an earlier recording, or the publisher restarted): frames whose name "
                                "is taken are saved as frame_SEQ_2.png, _3, ...", path)
                continue
            except OSError as exc:
                raise EdiLiveError(f"cannot write {path}: {exc.strerror or exc}") from exc
            try:
                with fh:
                    fh.write(png.tobytes())
            except OSError as exc:  # a full disk: no truncated PNG among the good ones
                path.unlink(missing_ok=True)
                raise EdiLiveError(f"cannot write {path}: {exc.strerror or exc}") from exc
            break

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None


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
    return fmt.format(value * scale) if isinstance(value, (int, float)) else "-"


STATS_STALE_S = 3.0  # the node sends stats once a second: older ones describe a node that stopped or went away


def status_line(rates: Rates, skipped: int, stats: dict | None, stats_age_s: float = 0.0) -> str:
    parts = [f"recv {rates.fps:6.1f} fps"]
    if stats and stats_age_s > STATS_STALE_S:
        parts.append(f"no stats from the node for {stats_age_s:.0f} s (stopped, or unreachable?)")
    elif stats:
        c = _num(stats, "c") if "c" in stats else f"{_num(stats, 'c_on')}/{_num(stats, 'c_off')}"
        parts.append(f"node {_num(stats, 'frames_per_s', fmt='{:.1f}')} fps, "
                     f"{_num(stats, 'events_per_s', 1e-6)} Mev/s, c {c}")
        parts.append(f"latency p50 {_num(stats, 'latency_p50_us', 1e-3)} ms p99 "
                     f"{_num(stats, 'latency_p99_us', 1e-3)} ms")
        # all of the node's drops (source, ring, publisher), not only the publisher's
        drops_key = "drops" if "drops" in stats else "publish_dropped"
        parts.append(f"node drops {_num(stats, drops_key, fmt='{:.0f}')}")
        if isinstance(stats.get("pred_psnr_db"), (int, float)):  # the live quality figure (docs/quality.md)
            parts.append(f"predicts next APS frame {_num(stats, 'pred_psnr_db', fmt='{:.1f}')} dB "
                         f"(nothing moved: {_num(stats, 'still_psnr_db', fmt='{:.1f}')} dB)")
    else:
        parts.append("no stats yet")
    parts.append(f"lost {rates.lost}, skipped {skipped}")
    return " | ".join(parts)


def parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with PORT 0-65535, e.g. 127.0.0.1:8080 (got {text!r})")
    return host, int(port)


def _number(kind: type, low: float, high: float | None = None) -> Any:
    """An argparse type: a number of `kind` in [low, high] (high None: no upper bound)."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or value != value or value < low or (high is not None and value > high) \
                or value == float("inf"):
            bound = f"from {low} to {high}" if high is not None else f">= {low}"
            what = "an integer" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"expected {what} {bound} (got {text!r})")
        return value

    return parse


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
    out.add_argument("--mp4-fps", type=_number(float, 0.1), default=30.0, metavar="FPS",
                     help="frame rate stored in the MP4 (default 30)")
    out.add_argument("--png", type=Path, metavar="DIR", help="also write every shown frame as DIR/frame_SEQ.png")
    out.add_argument("--jpeg-quality", type=_number(int, 1, 100), default=85, metavar="Q",
                     help="MJPEG quality 1-100 (default 85)")
    run = parser.add_argument_group("run")
    run.add_argument("--duration", type=_number(float, 0.001), metavar="SECONDS",
                     help="stop after this long (default: Ctrl-C)")
    run.add_argument("--max-frames", type=_number(int, 1), metavar="N", help="stop after N frames")
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
        skipped_before = self.sub.skipped
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
            self.rates.add(header["seq"], self.sub.skipped - skipped_before)
            self.hub.put(image)
            self.recorder.write(header, image)
        if self.rates.tick():
            line = status_line(self.rates, self.sub.skipped, self.sub.last_stats,
                               time.monotonic() - self._stats_at)
            self.hub.status = {"viewer_fps": round(self.rates.fps, 1), "lost": self.rates.lost,
                               "skipped": self.sub.skipped, "line": line, "node": self.sub.last_stats}
            if not self.args.quiet:
                try:
                    sys.stderr.write(f"\r{line}\x1b[K" if self._tty else line + "\n")
                    sys.stderr.flush()
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
            sys.stderr.write("\n")
        saved = f", {self.recorder.written} saved" if (self.args.mp4 or self.args.png) else ""
        if self.recorder.skipped_size:
            saved += f" ({self.recorder.skipped_size} left out of the MP4: another size than its first frame)"
        log.info("received %d frames (lost %d, skipped %d, bad %d)%s", self.rates.frames, self.rates.lost,
                 self.sub.skipped, self.bad_messages, saved)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="viewer: %(message)s")
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
