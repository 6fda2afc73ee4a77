"""Deblurring ahead (exposure_ahead.py): the double integral run while the next exposure's events arrive gives
frames bit-identical to reading the exposure's events at its end, and it is really used on a regular stream. Fed
the way the worker feeds a reconstructor: events in chunks as they come, each APS frame some time after its
exposure ended, with every event from its exposure start on."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate


def _scene(seed=2, **kw):
    cfg = dict(width=48, height=36, duration_s=0.32, exposure_us=12_000, frame_interval_us=20_000,
               velocity_px_s=(150.0, 40.0), seed=seed)
    cfg.update(kw)
    return simulate(SceneConfig(**cfg))


def _drive(sim, rec, chunk=300, delay_us=1_000, gap_at=None, every_render=1, in_batch=False, skip=()):
    """(deblurred images, latent images) of `rec` fed like the worker does. `delay_us`: how long after its exposure
    end a frame is handed over (the next exposure may have begun by then); `gap_at`: frame index before which the
    stream reports a gap; `in_batch`: the chunk that crosses the hand-over time goes only into the frame's batch
    (its exposure's last events reach the reconstructor with the frame, not before); `skip`: frame indices never
    deblurred (the worker skips the deblur of a static scene's frame)."""
    ev = sim.events
    t = ev["t"]
    frames = list(sim.frames)
    deblurred, latent = [], []
    pos, k, n_chunks = 0, 0, 0
    while pos < ev.size or k < len(frames):
        due = frames[k].exposure_end_us + delay_us if k < len(frames) else None
        end = min(pos + chunk, ev.size)
        if due is not None and (pos >= ev.size or t[end - 1] > due):
            if in_batch:
                f = frames[k]
                deblurred.append(rec.on_frame(f, edi.window(ev[:end], f.exposure_start_us, None)).image)
                k, pos = k + 1, end
                continue
            end = int(np.searchsorted(t, due, side="right"))
        if end > pos:
            rec.on_events(ev[pos:end])
            n_chunks += 1
            if rec.has_reference and n_chunks % every_render == 0:
                latent.append(rec.render().image)
            pos = end
        if due is not None and (pos >= ev.size or t[pos] > due):
            if k in skip:
                k += 1
                continue
            if gap_at == k:
                rec.mark_gap()
            f = frames[k]
            deblurred.append(rec.on_frame(f, edi.window(ev[:pos], f.exposure_start_us, None)).image)
            k += 1
    return deblurred, latent


@pytest.mark.parametrize("kw, drive", [
    ({}, {}),  # the regular stream
    ({"c": 0.2}, {}),  # a fixed c (no c estimation)
    ({"c_on": 0.22, "c_off": 0.17}, {}),  # two thresholds
    ({}, {"delay_us": 9_000}),  # frames handed over after the next exposure began: no prediction can start
    ({}, {"gap_at": 6}),  # a gap mid-stream
    ({"reestimate_every": 2}, {}),  # c re-estimated every other frame: deblurs overlap a change of c
    ({}, {"chunk": 37}),  # small, odd chunks
    ({}, {"in_batch": True, "delay_us": 0, "chunk": 101}),  # the exposure's last events come with the frame
    ({"c_on": 0.22, "c_off": 0.17}, {"in_batch": True, "delay_us": 0, "chunk": 101}),
])
def test_frames_are_bit_identical_with_and_without_deblurring_ahead(kw, drive):
    sim = _scene()
    cfg = sim.config
    # the driver hands frames over on the APS clock, so the event clock offset is held at 0 (a found offset moves
    # the windows once, and the prediction needs three regular ones again: fewer deblurs ahead, same frames)
    ahead = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=0, **kw)
    plain = EdiReconstructor(cfg.width, cfg.height, deblur_ahead=False, clock_offset_us=0, **kw)
    got, want = _drive(sim, ahead, **drive), _drive(sim, plain, **drive)
    assert len(got[0]) == len(sim.frames) and len(got[1]) > 10
    for a, b in zip(got[0] + got[1], want[0] + want[1]):
        assert np.array_equal(a, b)
    used = ahead.stats()["deblurs_ahead"]
    if drive.get("delay_us", 0) > cfg.frame_interval_us - cfg.exposure_us:
        assert used == 0
    elif drive.get("in_batch"):  # not when a frame's batch reached into the next exposure
        assert used >= len(sim.frames) // 2
    else:
        # every frame after the first three (the prediction needs three regular windows) but those after a gap; a
        # c re-estimated after a deblur re-arms the next integral with the new c (settle() runs before any event
        # is fed)
        assert used >= len(sim.frames) - 3 - (4 if "gap_at" in drive else 0)


def test_an_irregular_exposure_is_deblurred_from_its_events():
    sim = _scene()
    cfg = sim.config
    frames = list(sim.frames)
    # the 6th exposure is 2 ms shorter than the others: the prediction does not match, the events are read
    f = frames[5]
    frames[5] = type(f)(f.image, f.exposure_start_us + 2_000, f.exposure_end_us, f.start_us, f.end_us, f.seq)
    sim.frames[:] = frames
    ahead = EdiReconstructor(cfg.width, cfg.height)
    plain = EdiReconstructor(cfg.width, cfg.height, deblur_ahead=False)
    got, want = _drive(sim, ahead), _drive(sim, plain)
    assert all(np.array_equal(a, b) for a, b in zip(got[0] + got[1], want[0] + want[1]))
    assert ahead._ahead.missed >= 1


@pytest.mark.parametrize("drive", [{}, {"skip": (8, 14)}, {"gap_at": 8}])
def test_hot_pixel_counts_are_the_same_when_a_running_integral_is_not_used(drive):
    # a masked (hot) pixel's events are counted toward the hot-pixel rates; a running integral fed for a window
    # that is then not deblurred from it (c re-estimated, a frame skipped, a gap) must not have counted them
    sim = _scene(seed=3, duration_s=0.5, hot_pixels=4, hot_rate_hz=400.0, noise_rate_hz=2.0)
    cfg = sim.config
    ahead = EdiReconstructor(cfg.width, cfg.height)
    plain = EdiReconstructor(cfg.width, cfg.height, deblur_ahead=False)
    got, want = _drive(sim, ahead, **drive), _drive(sim, plain, **drive)
    assert ahead.hot_pixels > 0 and ahead._ahead.used > 0
    assert ahead._ahead.missed > 0 or "gap_at" in drive
    for a, b in zip(got[0] + got[1], want[0] + want[1]):
        assert np.array_equal(a, b)
    assert np.array_equal(ahead._hot._counts, plain._hot._counts)  # the frames to come depend on them


def test_a_combined_mask_that_does_not_change_does_not_stop_the_deblur_ahead():
    """Hot and flickering pixels make the ignored-pixel mask a combination of masks, rebuilt as a new array at
    every exposure end: never the very mask the next integral was armed with, it once stopped every deblur ahead
    (now the integral adopts it, RunningDivisor.remask)."""
    from edi_live.simulation import preset

    sim = simulate(preset("demo", duration_s=0.6))  # its noise makes a few hot and a few flicker-timed pixels
    cfg = sim.config
    ahead = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=0)
    plain = EdiReconstructor(cfg.width, cfg.height, deblur_ahead=False, clock_offset_us=0)
    got, want = _drive(sim, ahead), _drive(sim, plain)
    stats = ahead.stats()
    assert stats["flicker_pixels"] > 0 and stats["hot_pixels"] > 0, "two masks combined"
    for a, b in zip(got[0] + got[1], want[0] + want[1]):
        assert np.array_equal(a, b)
    assert stats["deblurs_ahead"] >= len(sim.frames) - 4


def test_a_mask_that_changes_between_exposures_is_taken_over_by_the_running_integral():
    """A lamp's pixels are flagged and released by the flicker detector from one exposure to the next, so the mask
    the next integral was armed with is rarely the deblur's: the integral adopts the new one (remask) and the
    frames stay bit-identical to reading the events at exposure end."""
    sim = _scene(seed=4, width=64, height=48, duration_s=0.4, flicker_hz=100.0)
    cfg = sim.config
    ahead = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=0)
    plain = EdiReconstructor(cfg.width, cfg.height, deblur_ahead=False, clock_offset_us=0)
    got, want = _drive(sim, ahead), _drive(sim, plain)
    assert ahead.stats()["flicker_pixels"] > 0, "the lamp's pixels are masked"
    for a, b in zip(got[0] + got[1], want[0] + want[1]):
        assert np.array_equal(a, b)
    assert ahead._ahead.remasked > 0
    assert ahead.stats()["deblurs_ahead"] >= len(sim.frames) - 5
