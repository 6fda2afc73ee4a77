"""Lone changes in latent frames (edi.lone): the whole-frame test against its definition written out pixel by pixel,
where a latent image's pixels start (references, restarts, fall-backs, the streaming copy), and what the
reconstructor shows with it."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.edi.lone import LONE_EPS
from edi_live.latent_state import LatentState
from edi_live.reconstructor import EdiReconstructor


def _brute_lone(log_lat, log_start, display, start_display, need, eps):
    """The definition one pixel at a time: a pixel whose change (float32 difference) is beyond eps and fewer than
    `need` of whose neighbours on the sensor changed the same way shows start_display."""
    h, w = log_lat.shape
    d = log_lat - log_start
    sign = np.where(d > eps, 1, np.where(d < -eps, -1, 0))
    out = display.copy()
    for y in range(h):
        for x in range(w):
            if sign[y, x] == 0:
                continue
            same = sum(sign[yy, xx] == sign[y, x] for yy in range(max(0, y - 1), min(h, y + 2))
                       for xx in range(max(0, x - 1), min(w, x + 2)) if (yy, xx) != (y, x))
            if same < need:
                out[y, x] = start_display[y, x]
    return out


@pytest.mark.parametrize("reference", [False, True])
def test_the_whole_frame_test_follows_its_definition(rng, reference):
    for _ in range(30):
        h, w = (int(v) for v in rng.integers(1, 16, 2))
        start = rng.normal(3.0, 1.5, (h, w)).astype(np.float32)
        lat = start.copy()
        moved = rng.random((h, w)) < rng.uniform(0.05, 0.6)
        lat[moved] += rng.choice([-0.4, -0.2, 0.3], int(moved.sum())).astype(np.float32)
        lat[rng.random((h, w)) < 0.05] += np.float32(1e-6)  # float residue of steps that cancelled: no change
        display, start_display = edi.to_uint8(lat), rng.integers(0, 256, (h, w)).astype(np.uint8)
        need = int(rng.integers(1, 4))
        with edi.numpy_reference() if reference else contextlib.nullcontext():
            got = edi.lone_changes_u8(lat, start, display, start_display, need=need)
        assert np.array_equal(got, _brute_lone(lat, start, display, start_display, need, LONE_EPS))


def test_every_frame_redone_only_in_the_tiles_near_its_events_is_the_whole_frame_test(rng):
    """LoneChanges redoes the test only in the 8x8 tiles near the events since the previous frame: at every frame
    cut of a stream of small clusters (which mark a few tiles each, partial tiles at the right and bottom edges
    included), after restarts, the fall-back to the APS and a rewritten display, the frame shown is the definition
    applied to the whole image, and most tiles were not redone."""
    w, h = 45, 29
    image = rng.integers(20, 230, (h, w)).astype(np.uint8)
    empty = (np.empty(0, np.int64), np.empty(0, np.float32), np.empty(0, np.float32))
    state = LatentState(w, h, lone_changes=True)
    state.set_reference(image, edi.ApsResponse(), empty, (0.3, 0.2))
    start, start_display = state.log_lat.copy(), state.display.copy()
    checked = 0

    def frame(k, i):
        nonlocal checked
        expected = _brute_lone(state.log_lat, start, state.display, start_display, 2, LONE_EPS)
        assert np.array_equal(state.shown_image(), expected), f"frame {k} at event {i}"
        checked += 1

    for step in range(40):
        n = int(rng.integers(1, 12))
        ev = np.zeros(n, EVENT_DTYPE)
        ev["t"] = step * 100 + np.arange(n)
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        ev["x"] = np.clip(cx + rng.integers(-1, 2, n), 0, w - 1)
        ev["y"] = np.clip(cy + rng.integers(-1, 2, n), 0, h - 1)
        ev["p"] = rng.random(n) < 0.5
        state.apply_with_frames(ev, sorted({int(c) for c in rng.integers(1, n + 1, 2)}), (0.3, 0.2), None, False,
                                frame)
        if step == 15:
            restarted = rng.choice(w * h, 8, replace=False)
            state.restart_pixels(restarted)
            start.reshape(-1)[restarted] = state.log_lat.reshape(-1)[restarted]
            start_display.reshape(-1)[restarted] = state.display.reshape(-1)[restarted]
        if step == 25:
            fallen = np.zeros((h, w), bool)
            fallen[3:6, 40:45] = True
            state.fall_back_to_aps(fallen, np.full((h, w), 60.0, np.float32), np.zeros((h, w), np.uint8))
            start[fallen], start_display[fallen] = state.log_lat[fallen], state.display[fallen]
        if step == 30:
            state.log_lat += np.float32(0.25)
            state.refresh_display()
        frame("end", step)
    tiles = 6 * 4
    assert checked > 40 and state._lone.tiles_updated < checked * tiles / 3


def test_the_numpy_reference_is_the_whole_frame_test_whenever_it_is_entered(rng, monkeypatch):
    """Inside edi.numpy_reference() a state made outside it shows the numpy whole-frame test (not the kernel that
    the reference is there to check), and back outside the tiles give the definition again. From the review."""
    import edi_live.edi._kernels_lone as kernels

    w, h = 21, 13
    empty = (np.empty(0, np.int64), np.empty(0, np.float32), np.empty(0, np.float32))
    state = LatentState(w, h, lone_changes=True)
    state.set_reference(rng.integers(20, 230, (h, w)).astype(np.uint8), edi.ApsResponse(), empty, (0.3, 0.2))
    start, start_display = state.log_lat.copy(), state.display.copy()
    compiled = kernels.update_tiles
    for step in range(6):
        state.apply(_events(rng, 30, w, h, step * 100), (0.3, 0.2), None, count=False, move=True)
        expected = _brute_lone(state.log_lat, start, state.display, start_display, 2, LONE_EPS)
        if step % 2:
            with edi.numpy_reference():
                monkeypatch.setattr(kernels, "update_tiles", None)  # calling it would raise
                assert np.array_equal(state.shown_image(), expected)
            monkeypatch.setattr(kernels, "update_tiles", compiled)
        else:
            assert np.array_equal(state.shown_image(), expected)


def test_a_lone_dot_shows_its_start_and_a_moving_patch_or_edge_stays():
    start = np.full((12, 16), np.log(100.0), np.float32)
    lat = start.copy()
    lat[2, 3] += 0.4  # a lone ON step
    lat[6:9, 5:8] -= 0.3  # a 3x3 patch darkens
    lat[1, 10:15] += 0.4  # a one-pixel-wide line: its ends have one neighbour on it
    lat[9, 12], lat[9, 13] = lat[9, 12] + 0.4, lat[9, 13] - 0.4  # neighbours moving opposite ways
    display, start_display = edi.to_uint8(lat), edi.to_uint8(start)
    got = edi.lone_changes_u8(lat, start, display, start_display)
    changed = got != display
    assert changed[2, 3] and got[2, 3] == 100
    assert not changed[6:9, 5:8].any()
    assert not changed[1, 11:14].any() and changed[1, 10] and changed[1, 14]
    assert changed[9, 12] and changed[9, 13] and got[9, 12] == got[9, 13] == 100
    assert changed.sum() == 5


def _events(rng, n, w, h, t0=0):
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = t0 + np.arange(n)
    cx, cy = rng.integers(0, w), rng.integers(0, h)  # half of them clustered (edges), half scattered (dots)
    ev["x"] = np.where(rng.random(n) < 0.5, np.clip(cx + rng.integers(-2, 3, n), 0, w - 1), rng.integers(0, w, n))
    ev["y"] = np.where(rng.random(n) < 0.5, np.clip(cy + rng.integers(-2, 3, n), 0, h - 1), rng.integers(0, h, n))
    ev["x"][:3] = w + 1  # off the sensor: skipped
    ev["p"] = rng.random(n) < 0.5
    return ev


def test_the_shown_image_is_the_test_against_where_each_pixel_started(rng):
    """LatentState with lone_changes: after a reference, events (in frame pieces and plain batches, with a mask),
    restarts of flagged pixels and the fall-back to the APS, the image it shows is lone_changes_u8 against the latent
    image at the reference, or where a pixel started again since; the display and log image are those of a state
    without it."""
    w, h = 13, 9
    image = rng.integers(20, 230, (h, w)).astype(np.uint8)
    empty = (np.empty(0, np.int64), np.empty(0, np.float32), np.empty(0, np.float32))
    states = [LatentState(w, h, lone_changes=True), LatentState(w, h)]
    for state in states:
        state.set_reference(image, edi.ApsResponse(), empty, (0.3, 0.2))
    lone = states[0]
    start, start_display = lone.log_lat.copy(), lone.display.copy()
    mask = np.zeros(w * h, bool)
    mask[rng.choice(w * h, 10, replace=False)] = True
    for step in range(12):
        ev = _events(rng, int(rng.integers(5, 60)), w, h, step * 1000)
        restarted, fallen = rng.choice(w * h, 6, replace=False), rng.random((h, w)) < 0.2
        for state in states:
            if step % 3 == 0:
                state.apply_with_frames(ev, [len(ev) // 3, 2 * len(ev) // 3], (0.3, 0.2), mask, True,
                                        lambda k, i: None)
            else:
                state.apply(ev, (0.3, 0.2), None if step % 2 else mask, count=False, move=True)
            if step == 5:
                state.restart_pixels(restarted)
            if step == 8:
                state.fall_back_to_aps(fallen, np.full((h, w), 60.0, np.float32), np.zeros((h, w), np.uint8))
        if step == 5:
            start.reshape(-1)[restarted] = lone.log_lat.reshape(-1)[restarted]
            start_display.reshape(-1)[restarted] = lone.display.reshape(-1)[restarted]
        if step == 8:
            start[fallen], start_display[fallen] = lone.log_lat[fallen], lone.display[fallen]
        assert np.array_equal(lone.log_lat, states[1].log_lat) and np.array_equal(lone.display, states[1].display)
        expected = _brute_lone(lone.log_lat, start, lone.display, start_display, 2, LONE_EPS)
        assert np.array_equal(lone.shown_image(), expected)
        if step == 7:
            assert (expected != lone.display).any()  # the test did hide something
    twin = lone.streaming_copy()
    twin.apply(_events(rng, 40, w, h), (0.3, 0.2), None, count=False, move=True)
    assert np.array_equal(twin.shown_image(), _brute_lone(twin.log_lat, start, twin.display, start_display, 2,
                                                          LONE_EPS))
    lone.restart_pixels(np.arange(w))  # the original's restart is not the copy's
    assert np.array_equal(twin.shown_image(), _brute_lone(twin.log_lat, start, twin.display, start_display, 2,
                                                          LONE_EPS))


def _still_frame(width=24, height=18):
    return Frame(image=np.full((height, width), 120, np.uint8), exposure_start_us=1_000, exposure_end_us=21_000)


@pytest.mark.parametrize("reference", [False, True])
def test_latent_denoise_hides_one_pixels_event_after_the_exposure_but_not_a_moving_patch(reference):
    """The reconstructor with latent_denoise: an event at one pixel after te leaves the latent frame at the value of
    te there; events at a 3x3 patch show as without it; the deblurred frame and the latent image are not changed."""
    after = np.zeros(10, EVENT_DTYPE)
    after["t"] = np.arange(25_000, 25_010)
    after["x"][0], after["y"][0] = 3, 3  # the lone one
    after["x"][1:], after["y"][1:] = 12 + np.arange(9) % 3, 8 + np.arange(9) // 3
    after["p"] = True
    images = {}
    for denoise in (False, True):
        with edi.numpy_reference() if reference else contextlib.nullcontext():
            rec = EdiReconstructor(24, 18, c=0.3, latent_denoise=denoise, black_level=0.0, clock_offset_us=0)
            deblurred = rec.on_frame(_still_frame(), np.zeros(0, EVENT_DTYPE)).image.copy()
            rec.on_events(after, 0)
            images[denoise] = (deblurred, rec.render().image.copy(), rec.latent_log_image)
    (deb_p, lat_p, log_p), (deb_d, lat_d, log_d) = images[False], images[True]
    assert np.array_equal(deb_p, deb_d) and np.array_equal(log_p, log_d)
    assert lat_p[3, 3] > 120 and lat_d[3, 3] == 120
    assert np.array_equal(lat_d[8:11, 12:15], lat_p[8:11, 12:15]) and (lat_p[8:11, 12:15] > 120).all()
    others = np.ones_like(lat_p, bool)
    others[3, 3] = False
    assert np.array_equal(lat_d[others], lat_p[others])


def test_a_colour_mosaic_or_another_mode_is_not_filtered():
    """A Bayer mosaic's neighbours are other colours: the reconstructor leaves its frames as they are; the node
    gives the option to causal mode only (cli warns in the others)."""
    from edi_live.config import NodeConfig
    from edi_live.node import default_reconstructor

    frame = Frame(image=np.full((18, 24), 120, np.uint8), exposure_start_us=1_000, exposure_end_us=21_000)
    after = np.zeros(1, EVENT_DTYPE)
    after["t"], after["x"], after["y"], after["p"] = 25_000, 3, 3, True
    latent = {}
    for denoise in (False, True):
        rec = EdiReconstructor(24, 18, c=0.3, latent_denoise=denoise, color_filter="RGGB", gray=True,
                               black_level=0.0, clock_offset_us=0)
        rec.on_frame(frame, np.zeros(0, EVENT_DTYPE))
        rec.on_events(after, 0)
        latent[denoise] = rec.render().image
    assert np.array_equal(latent[False], latent[True]) and latent[True][3, 3] > 120
    for mode, on in (("causal", True), ("nearest", False), ("fused", False)):
        cfg = NodeConfig.from_options({"device": "auto", "mode": mode, "latent_denoise": True})
        assert default_reconstructor(24, 18, cfg.edi).settings.latent_denoise is on
