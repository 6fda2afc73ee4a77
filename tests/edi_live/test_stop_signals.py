"""StopSignals: which signals stop the node, and that a hang-up ignored by `nohup` stays ignored."""

from __future__ import annotations

import signal

import pytest

from edi_live.stop_signals import StopSignals


@pytest.fixture
def hup_restored():
    before = signal.getsignal(signal.SIGHUP)
    yield
    signal.signal(signal.SIGHUP, before)


def test_a_hang_up_stops_the_node_like_sigterm(hup_restored):
    signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a terminal session: the default action kills on the spot
    stops = []
    signals = StopSignals()
    signals.install()
    try:
        # checked before raising it: unhandled, the hang-up would kill this very test process
        assert signal.getsignal(signal.SIGHUP) == signals._handle, "SIGHUP would kill the node on the spot"
        signals.attach(type("Node", (), {"stop": lambda self: stops.append(True)})())
        signal.raise_signal(signal.SIGHUP)
    finally:
        signals.restore()
    assert signals.received == "SIGHUP" and stops == [True]
    assert signal.getsignal(signal.SIGHUP) == signal.SIG_DFL  # restored after an in-process call


def test_nohup_keeps_the_hang_up_ignored(hup_restored):
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # what `nohup edi-live ...` hands us
    signals = StopSignals()
    signals.install()
    try:
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        assert signal.getsignal(signal.SIGINT) == signals._handle  # the others are still ours
    finally:
        signals.restore()
