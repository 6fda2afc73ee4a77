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


def test_sigterm_during_the_kernel_compile_ends_it_at_once_with_nothing_opened(monkeypatch, real_recordings,
                                                                                tmp_path):
    # a cold compile held SIGTERM for its 15-30 s (14 s measured here; more on a small computer, where a service
    # manager's stop timeout then kills the node): the signal handler only set a flag the compile never looked at
    from edi_live import cli, node

    went_on = []

    def compiling(make_reconstructor, edi_config):
        signal.raise_signal(signal.SIGTERM)  # as `systemctl stop` would, in the middle of the compile
        went_on.append("the compile went on after SIGTERM")

    monkeypatch.setattr(node, "warm_up", compiling)
    out = tmp_path / "sharp.aedat4"
    rc = cli.main(["--replay", str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--no-publish",
                   "--out", str(out)])
    assert rc == 0 and went_on == [] and not out.exists()
