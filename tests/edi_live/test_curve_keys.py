"""edi_live.curve_keys: ZeroMQ certificate files as the publisher (--curve-secret-key) and the subscribers
(--curve-server-key) read them, from a file, a pipe whose writer is done (bash's <(...)), or a FIFO that nothing
writes to, which must end with a clear error instead of blocking the reader for ever."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest
import zmq.auth

from edi_live import config_file
from edi_live.client import Subscriber
from edi_live.curve_keys import load_certificate
from edi_live.errors import ClientError, PublishError
from edi_live.publisher import Publisher, generate_curve_keys
from tests.helpers.pipes import written_pipe


def test_keys_are_those_zmq_wrote(tmp_path: Path):
    public_file, secret_file = generate_curve_keys(tmp_path)
    assert load_certificate(secret_file) == zmq.auth.load_certificate(secret_file)  # the oracle: pyzmq's reader
    assert load_certificate(public_file) == zmq.auth.load_certificate(public_file)


def test_a_key_through_a_pipe_whose_writer_is_done(tmp_path: Path):
    _, secret_file = generate_curve_keys(tmp_path)
    with written_pipe(secret_file.read_bytes()) as path:
        assert load_certificate(path) == zmq.auth.load_certificate(secret_file)


def test_a_file_without_a_public_key_is_refused(tmp_path: Path):
    bad = tmp_path / "notes.txt"
    bad.write_text("nothing here\n")
    with pytest.raises(ValueError, match="public-key"):
        load_certificate(bad)


def _outcome_in_thread(action, fifo: Path) -> list:
    """Run `action` on a thread; if it is still blocked after 20 s, release it (open the FIFO's write end) and
    fail."""
    outcome: list = []

    def run() -> None:
        try:
            outcome.append(action())
        except Exception as exc:  # noqa: BLE001 - the test inspects it
            outcome.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(20)
    if thread.is_alive():
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(5)
        pytest.fail("reading a key from a FIFO that nothing writes to did not end")
    return outcome


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_server_key_fifo_without_a_writer_is_a_client_error(tmp_path: Path, monkeypatch):
    # the subscriber blocked in open() for ever ('python -m edi_live.client --curve-server-key FIFO')
    monkeypatch.setattr(config_file, "PIPE_WAIT_S", 0.2)
    fifo = tmp_path / "server.key"
    os.mkfifo(fifo)
    outcome = _outcome_in_thread(lambda: Subscriber("tcp://127.0.0.1:9", curve_server_key=fifo), fifo)
    assert isinstance(outcome[0], ClientError) and "pipe" in str(outcome[0]), outcome


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_secret_key_fifo_without_a_writer_is_a_publish_error_naming_it(tmp_path: Path, monkeypatch):
    # the publisher's thread blocked in open() and the node said 'publisher did not bind ... within 10 s'
    monkeypatch.setattr(config_file, "PIPE_WAIT_S", 0.2)
    fifo = tmp_path / "server.key_secret"
    os.mkfifo(fifo)
    pub = Publisher(["tcp://127.0.0.1:*"], "cam", curve_secret_key=fifo)
    try:
        outcome = _outcome_in_thread(pub.start, fifo)
    finally:
        pub.close()
    assert isinstance(outcome[0], PublishError) and str(fifo) in str(outcome[0]) and "pipe" in str(outcome[0])


@pytest.mark.parametrize("line", ['public-key = "tooshort"', 'public-key = "' + '~' * 40 + '"',
                                  'public-key = "' + "a" * 39 + ' "'])
def test_a_key_that_is_not_z85_is_refused_when_read(tmp_path: Path, line):
    # it reached libzmq, whose 'Invalid argument' ended the client and the viewer with a traceback and the node
    # with 'the main thread failed: ZMQError: Invalid argument'
    bad = tmp_path / "server.key"
    bad.write_text(f"metadata\ncurve\n    {line}\n")
    with pytest.raises(ValueError, match="40-character Z85"):
        load_certificate(bad)
    with pytest.raises(ClientError, match="40-character Z85"):
        Subscriber("tcp://127.0.0.1:9", curve_server_key=bad)


def test_a_secret_key_that_is_not_z85_is_a_publish_error(tmp_path: Path):
    public_file, _ = generate_curve_keys(tmp_path)
    bad = tmp_path / "bad.key_secret"
    bad.write_bytes(public_file.read_bytes() + b'    secret-key = "alsoshort"\n')
    pub = Publisher(["tcp://127.0.0.1:*"], "cam", curve_secret_key=bad)
    try:
        with pytest.raises(PublishError, match="40-character Z85"):
            pub.start()
    finally:
        pub.close()


def test_a_key_given_as_40_characters_must_be_z85():
    with pytest.raises(ClientError, match="40-character Z85"):
        Subscriber("tcp://127.0.0.1:9", curve_server_key='"' * 40)
