"""LatentState: the fall-back to the APS at unreliable pixels, by table for a uint8 frame and by its formulas; the
start the lone-change test of latent frames compares with."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE
from edi_live.latent_state import LatentState


@pytest.mark.parametrize("black, gamma", [(0.0, 1.0), (12.5, 1.0), (3.0, 0.8), (0.0, 2.2)])
@pytest.mark.parametrize("reference", [False, True])
def test_the_fall_back_of_a_uint8_frame_by_table_equals_the_formulas_on_b(rng, black, gamma, reference):
    """At the marked pixels, L(f) = B: the uint8 frame's tables (a compiled pass, or its numpy reference) give the
    log images and their uint8 images bit for bit as the log formula on B (the frame's to_float) does; the other
    pixels keep what they held."""
    h, w = 180, 240
    image = rng.integers(0, 256, (h, w)).astype(np.uint8)
    image[0, :16], image[-1, :240] = np.arange(16), np.arange(16, 256)  # every value, at the start and the end
    pixels = rng.random((h, w)) < 0.1
    pixels[0, :16] = pixels[-1, :240] = True
    aps = edi.ApsResponse(black_level=black, gamma=gamma)
    b = aps.to_float(image)[0]
    states = []
    for table in (False, True):
        state = LatentState(w, h)
        init = np.random.default_rng(3)
        state.log_ref = init.uniform(-1, 5, (h, w)).astype(np.float32)
        state.log_lat[:] = init.uniform(-1, 5, (h, w))
        state.display[:] = init.integers(0, 256, (h, w))
        deblurred = init.integers(0, 256, (h, w)).astype(np.uint8)
        before = [a.copy() for a in (state.log_ref, state.log_lat, state.display, deblurred)]
        if not table:
            state.fall_back_to_aps(pixels, b, deblurred)
        elif reference:
            with edi.numpy_reference():
                edi.fall_back_u8(pixels, image, black, gamma, state.log_ref, state.log_lat, state.display, deblurred)
        else:
            state.fall_back_to_aps(pixels, b, deblurred, image, aps)
        after = [state.log_ref, state.log_lat, state.display, deblurred]
        for old, new in zip(before, after):
            assert np.array_equal(old[~pixels], new[~pixels])
            assert not np.array_equal(old[pixels], new[pixels])
        states.append(after)
    for by_formula, by_table in zip(*states):
        assert by_formula.dtype == by_table.dtype
        assert np.array_equal(by_formula.view(np.uint8), by_table.view(np.uint8))


def _state_at_a_reference(w=12, h=10, value=100):
    """A LatentState with lone_changes, just deblurred: a flat frame with no event, L(f) = B everywhere."""
    state = LatentState(w, h, lone_changes=True)
    image = np.full((h, w), value, np.uint8)
    empty = (np.empty(0, np.int64), np.empty(0, np.float32), np.empty(0, np.float32))
    state.set_reference(image, edi.ApsResponse(), empty, (0.3, 0.3))
    return state


def _one_event(x, y, on=True):
    ev = np.zeros(1, EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = x, y, on
    return ev


def test_a_restarted_or_fallen_back_pixel_starts_again_for_the_lone_change_test():
    """The start the test compares with is where the latent image (re)started: after a restart (a flicker flag) or a
    fall-back to the APS a pixel's later events count from there; the copy streaming from the previous reference
    keeps that reference's start."""
    state = _state_at_a_reference()
    assert np.array_equal(state.shown_image(), state.display)
    state.apply(_one_event(4, 4), (0.3, 0.3), None, count=False, move=True)
    assert state.display[4, 4] > 100 and state.shown_image()[4, 4] == 100  # a lone change
    twin = state.streaming_copy()
    state.log_shown = state.log_lat.copy()  # stands for an L(f) shown at the restart that holds the new value
    state.restart_pixels(np.array([4 * 12 + 4]))
    assert np.array_equal(state.shown_image(), state.display) and state.shown_image()[4, 4] > 100
    assert twin.shown_image()[4, 4] == 100  # its own start: the reference it streams from
    fallen = _state_at_a_reference()
    fallen.apply(_one_event(6, 2, on=False), (0.3, 0.3), None, count=False, move=True)
    pixels = np.zeros((10, 12), bool)
    pixels[2, 6] = True
    b = np.full((10, 12), 80.0, np.float32)
    fallen.fall_back_to_aps(pixels, b, np.zeros((10, 12), np.uint8))
    assert fallen.shown_image()[2, 6] == fallen.display[2, 6] == 80
