"""drivers.tcp_connect: a stop or the deadline ends a connect whose name lookup does not answer. A resolver that
never answers cannot be made on loopback, so getaddrinfo is replaced by one that blocks until the test releases
it (a real resolver behind a dead DNS server blocks the same way, uninterruptibly)."""

from __future__ import annotations

import socket
import threading
import time
from typing import Iterator

import pytest

from drivers import tcp_connect


@pytest.fixture
def hanging_lookup(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    """getaddrinfo blocks until the event is set (at teardown at the latest); returns the event 'lookup entered'."""
    entered, release = threading.Event(), threading.Event()
    real = socket.getaddrinfo

    def blocking(*args, **kwargs):  # noqa: ANN002, ANN003
        entered.set()
        release.wait()
        return real(*args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", blocking)
    yield entered
    release.set()


def test_a_stop_during_a_name_lookup_that_does_not_answer_ends_the_connect(hanging_lookup):
    stop = threading.Event()
    result: list = []
    connecting = threading.Thread(target=lambda: result.append(tcp_connect.connect("dv.example", 7777, 60, stop)),
                                  daemon=True)
    connecting.start()
    assert hanging_lookup.wait(10)
    stop.set()
    stopping = time.monotonic()
    connecting.join(5)
    assert not connecting.is_alive(), "the connect still waits for the name lookup after a stop"
    assert result == [None]
    assert time.monotonic() - stopping < 1.0


def test_a_name_lookup_that_does_not_answer_gives_up_at_the_connect_deadline(hanging_lookup):
    result: list = []

    def attempt() -> None:
        try:
            result.append(tcp_connect.connect("dv.example", 7777, 0.3, threading.Event()))
        except OSError as exc:
            result.append(exc)

    connecting = threading.Thread(target=attempt, daemon=True)
    connecting.start()
    connecting.join(5)
    assert not connecting.is_alive(), "the connect still waits for the name lookup after its deadline"
    assert isinstance(result[0], TimeoutError)
    assert "name lookup of dv.example did not answer within 0.3 s" in str(result[0])


def test_an_unknown_name_is_the_resolvers_own_error():
    with pytest.raises(socket.gaierror):
        tcp_connect.connect("no-such-host.invalid", 7777, 10, threading.Event())


def test_a_listener_on_loopback_is_connected():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        sock = tcp_connect.connect("localhost", server.getsockname()[1], 5, threading.Event())
        assert sock is not None
        with sock:
            peer, _ = server.accept()
            peer.close()
