"""`--mode nearest` hold-back: which latent times wait for the next APS frame (edi_live.nearest_mode). Through the
worker (every latent frame from the nearer APS frame, from the first interval on): test_worker.py."""

from __future__ import annotations

from edi_live.nearest_mode import NearestHoldBack


def test_without_a_known_interval_every_time_after_the_reference_is_held():
    hold = NearestHoldBack()
    assert not hold.should_hold(5_000, None)
    assert hold.should_hold(1_001, 1_000) and not hold.should_hold(1_000, 1_000)
    hold.new_reference(1_000, 21_000)
    assert not hold.should_hold(21_000 + 5_000, 21_000)  # a quarter interval: nearer the current reference
    assert hold.should_hold(21_000 + 10_001, 21_000)
    hold.gap()
    hold.new_reference(21_000, 500_000)  # across the gap: not an interval
    assert hold.interval_us is None and hold.should_hold(500_001, 500_000)
