"""A one-connection TCP server on loopback that plays a hostile or broken DV output: it sends given bytes to the
first client, then closes. For the DV network input's tests."""

from __future__ import annotations

import contextlib
import socket
import threading
from typing import Iterator


def serve_once(data: bytes, sent: threading.Event | None = None,
               release: threading.Event | None = None) -> tuple[int, threading.Thread]:
    """(port, server thread): the thread accepts one connection, sends `data`, sets `sent`, waits for `release`
    (when given, at most 10 s), then closes the connection and the server."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(10)

    def run() -> None:
        try:
            conn, _ = server.accept()
            with conn:
                conn.sendall(data)
                if sent is not None:
                    sent.set()
                if release is not None:
                    release.wait(10)
        except OSError:
            pass
        finally:
            server.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return server.getsockname()[1], thread


@contextlib.contextmanager
def one_shot_server(data: bytes, sent: threading.Event | None = None,
                    release: threading.Event | None = None) -> Iterator[str]:
    """serve_once as a context: yields the endpoint, and joins the server when the block ends."""
    port, thread = serve_once(data, sent, release)
    try:
        yield f"tcp://127.0.0.1:{port}"
    finally:
        thread.join(10)
