"""The viewer's live page: the newest frame shared between the receive loop and the HTTP threads (FrameHub), and
a ThreadingHTTPServer for / (the page), /stream.mjpg, /frame.jpg and /status.json (MjpegServer).

The stats shown come from the network: json_safe makes any map strict JSON (binary values, extension types,
non-finite floats, nesting past 32 levels).
"""

from __future__ import annotations

import html
import http.server
import json
import logging
import math
import threading
from typing import Any

import cv2
import numpy as np

from edi_live.errors import EdiLiveError
from tools.viewer_output import to_u8

log = logging.getLogger("edi-live-viewer")
BOUNDARY = "edi-live-frame"


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
