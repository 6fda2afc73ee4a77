"""edi_live.dv_output's client slots (max_clients, 10 as in DV): clients that connect and never read must not keep a
real viewer out, and clients that connect and close at once must not hold slots. Real loopback sockets."""

from __future__ import annotations

import contextlib
import socket
import struct

import numpy as np
import pytest

from edi_live.datatypes import Reconstruction
from edi_live.dv_output import DvOutput, parse_tcp_endpoint
from tests.helpers.polling import wait_until

T0 = 1_700_000_000_000_000


def _rec(t_us: int, value: int) -> Reconstruction:
    img = np.full((260, 346), value, np.uint8)
    return Reconstruction(img, t_us, "latent", t_us, t_us, t_us, 0.2, 0.2, 10)


def _idle_client(host: str, port: int) -> socket.socket:
    """A client that never reads, with a small receive buffer so that the server's queue for it fills soon."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, port))
    return sock


def _fill_every_queue(out: DvOutput) -> None:
    """Frames until every client's queue is full (it is losing packets): the server's view of a stalled client."""
    k = 0

    def full() -> bool:
        nonlocal k
        if out.pending() == 0 and all(len(c.queue) >= out.client_queue for c in list(out._clients.values())):
            return True
        out.submit(_rec(T0 + k, k % 200))
        k += 1
        return False

    wait_until(full)


def _first_packet(sock: socket.socket, timeout_s: float = 5.0) -> bytes:
    """The IOHeader and the first packet's head, as a DV client reads them (b"" if the server closed first)."""
    sock.settimeout(timeout_s)
    buf = b""
    while True:
        if len(buf) >= 4:
            need = 4 + int.from_bytes(buf[:4], "little") + 8
            if len(buf) >= need:
                return buf
        chunk = sock.recv(1 << 16)
        if not chunk:
            return buf
        buf += chunk


@contextlib.contextmanager
def _full_server(stall_s: float, fill: bool):
    """A DV output server each of whose slots a client that never reads holds (their queues full with `fill`):
    yields (the server, its host, its port, the idle clients' sockets)."""
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, client_queue=4, hold_s=0, stall_s=stall_s) as out:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        with contextlib.ExitStack() as idle_socks:
            idle = [idle_socks.enter_context(_idle_client(host, port)) for _ in range(out.max_clients)]
            wait_until(lambda: out.client_count() == out.max_clients)
            if fill:
                _fill_every_queue(out)
            yield out, host, port, idle


def test_a_new_client_takes_the_slot_of_a_client_that_stalled_and_the_stalled_one_is_named(caplog):
    with _full_server(stall_s=0, fill=True) as (out, host, port, idle):
        with caplog.at_level("INFO", logger="edi_live.dv_output"):
            viewer = socket.create_connection((host, port))
            wait_until(lambda: out.connections == out.max_clients + 1)
            with viewer:
                out.submit(_rec(T0 + 1_000_000, 9))
                got = _first_packet(viewer)
        assert len(got) > 4 + int.from_bytes(got[:4], "little"), "the viewer got no frame"
        assert out.client_count() == out.max_clients and out.error is None
        lines = [r.getMessage() for r in caplog.records if "to make room for" in r.getMessage()]
        names = {"%s:%d" % s.getsockname()[:2] for s in idle}
        assert len(lines) == 1 and "\n" not in lines[0], lines
        assert sum(name in lines[0] for name in names) == 1, lines[0]
        assert not [r for r in caplog.records if "refused" in r.getMessage()]


@pytest.mark.parametrize("frames", [False, True], ids=["idle-without-frames", "queues-full-but-not-for-long"])
def test_a_new_client_is_refused_when_no_client_has_stalled(caplog, frames):
    stall_s = 600 if frames else 0  # full queues, but for less than stall_s: not stalled
    with _full_server(stall_s=stall_s, fill=frames) as (out, host, port, _):
        with caplog.at_level("INFO", logger="edi_live.dv_output"):
            with socket.create_connection((host, port)) as late:
                assert _first_packet(late) == b""  # closed without a header: refused
        assert out.connections == out.max_clients and out.client_count() == out.max_clients
        assert any("refused DV client" in r.getMessage() for r in caplog.records)


def test_clients_that_connect_and_close_at_once_leave_every_slot_free():
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, hold_s=0) as out, contextlib.ExitStack() as good_socks:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        for k in range(100):
            sock = socket.create_connection((host, port))
            if k % 2:  # half of them reset the connection instead of closing it
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()
        good = [good_socks.enter_context(socket.create_connection((host, port))) for _ in range(out.max_clients)]
        wait_until(lambda: out.connections == 100 + out.max_clients and out.client_count() == out.max_clients)
        out.submit(_rec(T0, 5))
        for sock in good:
            got = _first_packet(sock)
            assert len(got) > 4 + int.from_bytes(got[:4], "little"), "a client got no frame"
        assert out.error is None
