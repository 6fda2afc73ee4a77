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
    """getaddrinfo blocks until teardown, then fails (no real lookup of the made-up name); yields the event 'lookup
    entered'. Teardown waits for the abandoned lookups to end: a later connect to the same name would wait for one
    still under way."""
    entered, release = threading.Event(), threading.Event()

    def blocking(*args, **kwargs):  # noqa: ANN002, ANN003
        entered.set()
        release.wait()
        raise socket.gaierror(socket.EAI_NONAME, "released by the test")

    monkeypatch.setattr(socket, "getaddrinfo", blocking)
    yield entered
    release.set()
    for thread in threading.enumerate():
        if thread.name.startswith("name lookup of"):
            thread.join(10)


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


def test_a_name_the_resolver_cannot_encode_is_an_oserror_naming_it_and_the_lookup_thread_fails_quietly(monkeypatch):
    """'a..b' (an empty label) makes getaddrinfo raise UnicodeError, not an OSError: it must reach the caller as
    one (the DV input turns an OSError into its one-line error), not die on the lookup thread (a traceback, and
    an IndexError for the caller)."""
    crashed: list = []
    monkeypatch.setattr(threading, "excepthook", crashed.append)
    with pytest.raises(OSError, match=r"a\.\.b"):
        tcp_connect.connect("a..b", 7777, 10, threading.Event())
    assert not crashed


def test_connects_that_give_up_on_a_lookup_still_under_way_wait_for_it_instead_of_starting_more(monkeypatch):
    """A resolver that never answers and a reconnect loop retrying every few seconds: each attempt used to leave
    one more lookup thread blocked for good."""
    calls, release = [], threading.Event()
    real = socket.getaddrinfo

    def blocking(*args, **kwargs):  # noqa: ANN002, ANN003
        calls.append(args)
        release.wait()
        return real(*args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", blocking)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        port = server.getsockname()[1]
        try:
            for _ in range(3):
                with pytest.raises(TimeoutError):
                    tcp_connect.connect("localhost", port, 0.05, threading.Event())
            assert len(calls) == 1
        finally:
            release.set()
            for thread in threading.enumerate():
                if thread.name == "name lookup of localhost":
                    thread.join(10)
        # once it has answered, the next connect looks the name up afresh
        sock = tcp_connect.connect("localhost", port, 5, threading.Event())
        assert sock is not None
        sock.close()
        assert len(calls) == 2
