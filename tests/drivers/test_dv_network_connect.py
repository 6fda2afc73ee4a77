"""drivers.dv_network's connecting: a peer that does not answer (its SYNs dropped) holds neither the opening nor a
reconnect past a stop. The peer is a loopback listener whose backlog is full: the kernel drops further SYNs, so a
connect to it waits as one to a host that is down or behind a dropping firewall."""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time
from typing import Iterator

import pytest

from drivers.dv_network import DvNetworkSource
from edi_live.aedat4.writer import info_xml, io_header
from edi_live.errors import DeviceNotFoundError
from tests.helpers.polling import wait_until


def _fill(port: int) -> socket.socket:
    """One connection into a backlog-0 listener, never accepted: the listener answers no further SYN (checked
    here; the test is skipped where a connect to it is refused or accepted instead)."""
    filler = socket.create_connection(("127.0.0.1", port), timeout=2)
    with socket.socket() as probe:  # (closed at once: its SYN is not sent again into a slot freed later)
        probe.settimeout(0.2)
        try:
            probe.connect(("127.0.0.1", port))
        except socket.timeout:
            return filler
        except OSError as exc:
            filler.close()
            pytest.skip(f"a full backlog is not a silent peer here ({exc})")
    filler.close()
    pytest.skip("a full backlog still accepts connections here")


@contextlib.contextmanager
def _unanswering_listener() -> Iterator[tuple[socket.socket, int]]:
    """(listener, port): a listener with backlog 0, full."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(0)
        port = server.getsockname()[1]
        with _fill(port):
            yield server, port


def _in_connect(thread: threading.Thread) -> bool:
    """True while `thread` runs inside drivers.dv_network's _Feed.connect (a state polled, not a sleep)."""
    frame = sys._current_frames().get(thread.ident)
    while frame is not None:
        if frame.f_code.co_name == "connect" and frame.f_code.co_filename.endswith("dv_network.py"):
            return True
        frame = frame.f_back
    return False


def test_a_stop_while_connecting_to_a_peer_that_does_not_answer_ends_the_opening_at_once():
    """stop() (Ctrl-C: the node calls it from the signal handler) while the opening waited for an unanswered SYN:
    the opening went on for the whole connect_timeout_s (5 s by default)."""
    outcome: list = []
    with _unanswering_listener() as (_, port):
        source = DvNetworkSource([f"tcp://127.0.0.1:{port}"], connect_timeout_s=30)

        def open_it() -> None:
            try:
                with source:
                    outcome.append(list(source))
            except BaseException as exc:  # noqa: BLE001 - the test reports it
                outcome.append(exc)

        opener = threading.Thread(target=open_it, daemon=True)
        opener.start()
        wait_until(lambda: _in_connect(opener))
        source.stop()
        stopping = time.monotonic()
        opener.join(5)
        took = time.monotonic() - stopping
    assert not opener.is_alive() and took < 1.0, f"the opening ended {took:.1f} s after stop()"
    assert outcome == [[]], outcome  # a stopped opening yields nothing, as a stop during the header does


def test_a_stop_while_reconnecting_to_a_peer_that_does_not_answer_ends_the_reader_at_once():
    header = io_header("none", -1, info_xml([(0, "EVTS", "events")], 32, 24, "DAVIS346_00000001", "none"))[0]
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(0)
        port = server.getsockname()[1]
        source = DvNetworkSource([f"tcp://127.0.0.1:{port}"], reconnect=True, connect_timeout_s=30, retry_s=0.01)
        opened = threading.Thread(target=source.__enter__, daemon=True)
        opened.start()
        conn, _ = server.accept()
        with conn:
            conn.sendall(header)
            opened.join(10)
            assert not opened.is_alive()
            filler = _fill(port)  # before the connection ends: the reconnect finds the listener full
        try:
            reader = source._feeds[0].thread
            wait_until(lambda: _in_connect(reader))  # the connection ended; reconnecting to a silent peer
            source.stop()
            stopping = time.monotonic()
            source.__exit__(None, None, None)
            took = time.monotonic() - stopping
        finally:
            filler.close()
    assert not reader.is_alive() and took < 1.0, f"the reader ended {took:.1f} s after stop()"


def test_a_peer_that_does_not_answer_is_one_line_after_connect_timeout_s():
    with _unanswering_listener() as (_, port):
        with pytest.raises(DeviceNotFoundError) as err:
            with DvNetworkSource([f"tcp://127.0.0.1:{port}"], connect_timeout_s=0.3):
                pass
    message = str(err.value)
    assert "\n" not in message and f"tcp://127.0.0.1:{port}" in message and "0.3 s" in message, message
