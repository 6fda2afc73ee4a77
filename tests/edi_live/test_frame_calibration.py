"""The calibration work a deblurred frame does not wait for (frame_calibration, EdiReconstructor.settle): settled
at once or left to the next call, the frames are the same; a c decided after frame k is used from frame k+1 on;
the first estimate still comes before the deblur that needs it."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.reconstructor import EdiReconstructor
from tests.edi_live.edi_scenes import make_scene
from tests.edi_live.test_reconstructor import stream

TRUE_C = 0.32
C_INIT = 0.2


@pytest.fixture(scope="module")
def scene():
    return make_scene("brick", c_on=TRUE_C, width=80, height=60, n_frames=8, sigma_c=0.02, seed=5)


def test_settled_at_once_or_later_the_frames_are_the_same(scene):
    kw = {"reestimate_every": 1}  # a re-estimation on every frame: c moves often
    now, later = _stream(scene, True, **kw), _stream(scene, False, **kw)
    assert len(now[0]) == len(scene.frames) and len(now[1]) > 20
    cs = {(r.c_on, r.c_off) for r in now[0]}
    assert len(cs) >= 3, "the scene must make c change more than once, or the test shows nothing"
    for a, b in zip(now[0], later[0]):
        assert (a.c_on, a.c_off) == (b.c_on, b.c_off)
        assert np.array_equal(a.image, b.image)
    for a, b in zip(now[1], later[1]):
        assert np.array_equal(a, b)


def _stream(scene, settle, **knobs):
    rec = EdiReconstructor(scene.width, scene.height, c_init=C_INIT, **knobs)
    latent = []
    outs = stream(scene, rec, on_latent=lambda r, t, ev: latent.append(r.render().image), settle=settle)
    return outs, latent, rec


def test_a_c_decided_after_frame_k_is_used_from_frame_k_plus_1(scene):
    rec = EdiReconstructor(scene.width, scene.height, c_init=C_INIT, reestimate_every=1)
    decided, used = [], []
    for k, frame in enumerate(scene.frames):
        out = _frame(scene, rec, k)
        used.append((out.c_on, out.c_off))
        assert (rec.c_on, rec.c_off) == used[-1], "c does not change between frames"
        rec.settle()
        assert (rec.c_on, rec.c_off) == used[-1], "settle() decides c but leaves it for the next frame"
        decided.append(rec._policy.c)
    changes = [k for k in range(2, len(used)) if decided[k] != used[k]]
    assert len(changes) >= 2, "re-estimations must change c for this test to mean anything"
    assert used[1] != decided[0], "frame 1 (the first pair) is deblurred with the start-up estimate"
    assert used[2:] == decided[1:-1]


def _frame(scene, rec, k):
    """Frame k of the scene with the events up to its exposure end (those before it were given to on_events)."""
    ev, t = scene.events, scene.events["t"]
    frame = scene.frames[k]
    lo = int(np.searchsorted(t, scene.frames[k - 1].exposure_end_us, side="right")) if k else 0
    hi = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
    start = int(np.searchsorted(t, frame.exposure_start_us, side="left"))
    if k:
        rec.on_events(ev[lo:max(lo, start)])
    return rec.on_frame(frame, ev[start:hi])


def test_the_first_estimate_comes_before_the_deblur_that_needs_it(scene):
    rec = EdiReconstructor(scene.width, scene.height, c_init=C_INIT)
    first = _frame(scene, rec, 0)  # no pair yet: deblurred with the initial c
    assert first.c_on == C_INIT
    rec.settle()
    second = _frame(scene, rec, 1)  # the first pair: c estimated before this deblur, not after it
    assert rec.reestimations == 1
    assert abs(second.c_on - TRUE_C) < 0.5 * abs(C_INIT - TRUE_C), (second.c_on, TRUE_C)
