"""edi_live.frame_order against its oracle, the emitted frames sorted by time: streams emitted as the causal worker
emits them (an APS frame's deblurred frame after the latent frames that the previous reference kept streaming
while it was deblurred), for the file's rule (--out) and the live stream's (--dv-output), with the wall clock given
explicitly."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.datatypes import Reconstruction
from edi_live.frame_order import FrameOrder

_IMAGE = np.zeros((2, 2), np.uint8)


def _rec(t: int, kind: str, ref: int) -> Reconstruction:
    return Reconstruction(_IMAGE, t, kind, ref, ref - 10, ref + 10, 0.2, 0.2, 1)


def causal_stream(rng: np.random.Generator, frames: int = 30,
                  lost: frozenset[int] = frozenset()) -> list[Reconstruction]:
    """APS frames every period; latent frames every few hundred µs from the newest reference the worker holds;
    each deblurred frame (t = f) emitted once its deblur ends, a random stretch of sensor time after f. The APS
    frames numbered in `lost` never become references (dropped on the way, or a static scene's skipped deblur)."""
    period = int(rng.integers(5_000, 40_000))
    out: list[Reconstruction] = []
    ref, t = 0, 0
    out.append(_rec(0, "deblurred", 0))
    for k in range(1, frames):
        f = k * period
        ready_at = f + int(rng.integers(0, period // 2 + period // 2 * (k % 5 == 0)))  # now and then a long one
        while True:
            t += int(rng.integers(50, 800))
            if t >= ready_at:
                break
            out.append(_rec(t, "latent", ref))  # from the previous reference, also after f
        if k in lost:
            continue
        out.append(_rec(f, "deblurred", f))
        ref = f
    return out


def _drain(order: FrameOrder, stream: list[Reconstruction], now=lambda i: 0.0) -> list[Reconstruction]:
    out: list[Reconstruction] = []
    for i, rec in enumerate(stream):
        order.add(rec, now(i))
        out += order.ready(now(i))
    return out + order.rest()


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("rule", ["file", "live"])
def test_every_frame_comes_out_once_and_in_time_order(seed, rule):
    rng = np.random.default_rng(seed)
    stream = causal_stream(rng)
    assert any(b.t_us < a.t_us for a, b in zip(stream, stream[1:])), "the stream has keyframes after newer frames"
    order = FrameOrder(100_000) if rule == "file" else FrameOrder(0, widen=False, predict=True)
    out = _drain(order, stream)
    expected = sorted(stream, key=lambda r: r.t_us)
    assert [r.t_us for r in out] == [r.t_us for r in expected] and order.late == 0
    assert sorted(map(id, out)) == sorted(map(id, stream))


@pytest.mark.parametrize("seed", range(6))
def test_a_lost_aps_frame_does_not_cost_the_live_rule_the_keyframe_after_the_next(seed):
    """Around a lost APS frame two references lie two periods apart: a prediction from that spacing alone let the
    latent frames past the next keyframe out before it, and that keyframe was late (dropped)."""
    stream = causal_stream(np.random.default_rng(seed), frames=30, lost=frozenset({6, 7, 15}))
    order = FrameOrder(0, widen=False, predict=True)
    out = _drain(order, stream)
    assert [r.t_us for r in out] == sorted(r.t_us for r in stream) and order.late == 0


def test_the_live_rule_lets_latent_frames_flow_and_holds_only_those_near_the_next_keyframe():
    rng = np.random.default_rng(7)
    stream = causal_stream(rng, frames=40)
    held = {}  # frames waiting, on average over the stream
    for predict in (False, True):
        order, total = FrameOrder(0, widen=False, predict=predict), 0
        for rec in stream:
            order.add(rec)
            order.ready()
            total += len(order)
        held[predict] = total / len(stream)
        assert order.late == 0
    assert held[True] < held[False] / 2, held


def test_a_keyframe_earlier_than_the_spacing_predicts_is_late_not_out_of_order():
    order = FrameOrder(0, widen=False, predict=True)
    out = []
    for rec in (_rec(0, "deblurred", 0), _rec(20_000, "deblurred", 20_000), _rec(31_000, "latent", 20_000),
                _rec(30_000, "deblurred", 30_000)):  # expected near 40000: 31000 went out before it
        order.add(rec)
        out += order.ready()
    out += order.rest()
    assert [r.t_us for r in out] == [0, 20_000, 31_000] and order.late == 1


def test_the_live_rule_releases_a_frame_as_soon_as_no_older_one_can_come():
    order = FrameOrder(0, widen=False)
    order.add(_rec(0, "deblurred", 0))
    order.add(_rec(500, "latent", 0))
    assert [r.t_us for r in order.ready()] == [0], "the keyframe: every later frame is newer"
    order.add(_rec(25_000, "latent", 0))  # after f1 = 20000, still from f0: f1 may yet come
    assert order.ready() == []
    order.add(_rec(20_000, "deblurred", 20_000))
    assert [r.t_us for r in order.ready()] == [500, 20_000]
    assert len(order) == 1


def test_the_hold_releases_the_longest_held_frame_and_what_is_older_than_it_in_time_order():
    order = FrameOrder(0, widen=False, hold_s=0.1)
    order.add(_rec(3_000, "latent", 0), now_s=10.0)
    order.add(_rec(1_000, "latent", 0), now_s=10.05)  # came later, but older
    assert order.ready(10.09) == [] and order.next_due_s() == pytest.approx(10.1)
    assert [r.t_us for r in order.ready(10.1)] == [1_000, 3_000], "3000 waited out its hold: 1000 goes first"
    order.add(_rec(3_500, "latent", 0), now_s=10.0)
    order.add(_rec(5_000, "latent", 0), now_s=10.05)
    order.add(_rec(4_000, "deblurred", 4_000), now_s=10.095)  # no older frame can come now
    assert [r.t_us for r in order.ready(10.095)] == [3_500, 4_000]
    assert order.next_due_s() == pytest.approx(10.15), "the longest held now: 5000, since 10.05"
    assert order.ready(10.149) == []
    assert [r.t_us for r in order.ready(10.15)] == [5_000]
    assert order.next_due_s() is None and len(order) == 0
    order.add(_rec(4_500, "latent", 4_000), now_s=10.2)  # older than 5000, already out: late
    assert order.ready(10.4) == [] and order.late == 1


def test_a_bounded_number_of_frames_is_held():
    order = FrameOrder(10**9, widen=False, max_held=3)
    out = []
    for t in range(10):
        order.add(_rec(1_000 + t, "latent", 0))
        out += order.ready()
        assert len(order) <= 3
    assert [r.t_us for r in out] == list(range(1_000, 1_007))


def test_the_file_rule_widens_its_window_to_the_disorder_it_saw():
    order = FrameOrder(0)
    for t in (0, 100, 200):
        order.add(_rec(t, "deblurred", t))
    order.add(_rec(150, "latent", 100))  # 50 µs of disorder: frames now wait 100 µs behind the newest
    assert [r.t_us for r in order.ready()] == [0], "100 is not yet 100 µs behind 200"
    order.add(_rec(260, "deblurred", 260))
    assert [r.t_us for r in order.ready()] == [100, 150]
