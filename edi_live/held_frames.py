"""Rendering the latent frames that `--mode nearest` and `--mode fused` held back until the next APS frame was
deblurred: from the nearest reference, or from both references around them. Runs on the worker thread; the
bookkeeping of what is held is in nearest_mode.py and fused_mode.py."""

from __future__ import annotations

import dataclasses

from edi_live.datatypes import Frame, Reconstruction
from edi_live.nearest_mode import NearestHoldBack
from edi_live.reconstruction import Reconstructor
from edi_live.ring import EventRing


def render_held(rec: Reconstructor, ring: EventRing, hold: NearestHoldBack, ref_f_us: int | None, t_us: int,
                arrival_ns: int) -> Reconstruction:
    """The latent image at t_us from the current reference, stamped with its arrival (the wait is recorded)."""
    f_us = ref_f_us if ref_f_us is not None else t_us
    lo, hi = min(t_us, f_us), max(t_us, f_us)
    events = ring.window(lo, hi + 1, end_index=ring.read_index)
    out = rec.render_from_reference(t_us, events)
    if arrival_ns:
        hold.waited(arrival_ns)
    return dataclasses.replace(out, arrival_ns=arrival_ns)


def before_new_reference(rec: Reconstructor, ring: EventRing, hold: NearestHoldBack, ref_f_us: int | None,
                         f_us: int) -> list[Reconstruction]:
    """Nearest mode, a new APS frame at f_us about to be deblurred: the held times nearer the current reference
    (before the midpoint), rendered from it while it is still the reference."""
    early = hold.take_before((ref_f_us + f_us) // 2 if ref_f_us is not None else None)
    return [render_held(rec, ring, hold, ref_f_us, t, a) for t, a in early]


def after_new_reference(rec: Reconstructor, ring: EventRing, hold: NearestHoldBack, ref_f_us: int, frame: Frame,
                        fused: bool) -> list[Reconstruction]:
    """Once the new reference at ref_f_us is deblurred: the times still held, from it (fused: from both)."""
    if fused:
        return render_fused(rec, ring, hold, ref_f_us, frame)
    return [render_held(rec, ring, hold, ref_f_us, t, a) for t, a in hold.take_all()]


def render_rest(rec: Reconstructor, ring: EventRing, hold: NearestHoldBack, ref_f_us: int | None) -> list:
    """Every held time at the end of the stream, from the current reference: the times after it in one forward
    pass (rec.render_fused without a previous reference), any others one by one."""
    done = hold.take_all()
    if ref_f_us is None:
        return []
    after = [d for d in done if d[0] > ref_f_us]
    out = [render_held(rec, ring, hold, ref_f_us, t, a) for t, a in done if t <= ref_f_us]
    if after:
        events = ring.window(ref_f_us + 1, after[-1][0] + 1, end_index=ring.read_index)
        out.extend(_stamped(rec.render_fused(None, None, None, [t for t, _ in after], events), after, hold))
    return out


def _stamped(recs: list[Reconstruction], held: list[tuple[int, int]], hold: NearestHoldBack) -> list[Reconstruction]:
    for _, a in held:
        if a:
            hold.waited(a)
    return [dataclasses.replace(r, arrival_ns=a) for r, (_, a) in zip(recs, held)]


def render_fused(rec: Reconstructor, ring: EventRing, hold, ref_f_us: int, frame: Frame) -> list[Reconstruction]:
    """The held times up to the new reference, from it and the previous one (forward from the new one when there
    is no previous: the first frame, after a gap); the new reference is kept for the next pair."""
    done = hold.take_until(ref_f_us)
    previous, hold.previous = hold.previous, (rec.reference_log(), frame.image)
    if previous is None or not done:
        return [render_held(rec, ring, hold, ref_f_us, t, a) for t, a in done]
    (log0, f0), image0 = previous
    # context before f0 (the residual estimate needs each pixel's last event, unless the last pair's pass carries
    # on) and what arrived after f1 (its next event after a time): edi_live.edi.residual_schedule
    # every time here is in the event clock: the frame's exposure end is moved by the offset that placed ref_f_us
    end = ref_f_us + (frame.exposure_end_us - frame.mid_exposure_us) + 1
    events = ring.window(rec.fused_events_from(f0, ref_f_us), end, end_index=ring.read_index)
    return _stamped(rec.render_fused((log0, f0), image0, frame.image, [t for t, _ in done], events), done, hold)
