"""Two-frame latent images: forward EDI from L_k(f_k) and backward EDI from L_{k+1}(f_{k+1}) blended in the log
domain, per pixel, by how reliable each side is at t.

For f_k < t < f_{k+1}, per pixel (log domain, 8-bit scale):

    forward  F(t) = log L_k(f_k)     + E(f_k -> t)          E: c_on * n_on - c_off * n_off over the events
    backward Bk(t) = log L_{k+1}(f_{k+1}) - E(t -> f_{k+1})
    fused    log L(t) = (1 - w) F(t) + w Bk(t) = F(t) + w D,     D = Bk(t) - F(t) = log L_{k+1} - log L_k - E(f_k -> f_{k+1})

D, the two frames' disagreement, does not depend on t. The weight w of the backward side is the share of the
error the forward side has picked up by t, against the share the backward side still has to pick up. Each event
crossed adds the error of one threshold (mismatch and noise events alike), an ON event in proportion to c_on and
an OFF event to c_off: the "event mass" m(t) = c_on n_on(f_k -> t) + c_off n_off(f_k -> t), M over the whole
interval. Each reference also carries an error of its own (blur residue, APS noise), worth A units of event mass,
which time distance shares between the sides (tau = (t - f_k) / (f_{k+1} - f_k), in STEPS steps):

    w = (m(t) + A tau_q) / (M + A)          both frames informative (no events: w = tau_q)
    w = 0, resp. 1                          only frame k, resp. only frame k+1, informative (clipped or black)
    w = 0 at t <= f_k, 1 at t >= f_{k+1}    the fused video passes through both deblurred frames

tau_q = j / (STEPS - 1) on the j-th step (0 on the first, 1 on the last: no jump at the frames). Then each event moves log L by c_on (1 + s) or -c_off (1 - s),
s = D / (M + A): a per-pixel threshold correction towards frame k+1, so a latent frame costs what a forward one
does (O(new events)) plus, STEPS times per interval, one pass over the pixels for the time term tau_q A D/(M + A).
The plan is set up once per pair of frames (`fusion_plan`, O(events + pixels)); `fused_frames` renders a pair's
held times with it in one pass (or, with `forward_plan`, plain forward EDI after the last frame). A = 1 (5 events at c = 0.2) and
STEPS = 4 were chosen on the accuracy benchmark's scenes (tools/bench_modes.py; A in 0.5..2 is within 0.1 dB).

On top, each frame adds the sub-threshold residual estimate r(t) between a pixel's events (edi_live.edi.residual),
and the references enter the plan less what they already hold of it (its mean over RESIDUAL_SPAN of an interval
either side of their mid-exposure): log L(t) = fused(log L_k - r_k, log L_{k+1} - r_{k+1}; t) + r(t). Both use
only the events of fixed time ranges around t (residual_seen), so a frame near a reference comes out the same from
either pair of frames. The frames at exactly f_k and f_{k+1} are the deblurred frames themselves. With the kernels
a pair's frames with the estimate are rendered in one call, from its schedule of changes
(edi_live.edi.residual_schedule; a ResidualCarry passed from pair to pair spares most of the context before f_k); the
numpy reference renders frame by frame with ResidualTracker.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from edi_live.edi import _backend, _kernels_fused, _kernels_residual
from edi_live.edi._backend import LOG_MAX, LOG_MIN
from edi_live.edi.latent import event_delta, render_buckets, to_uint8
from edi_live.edi.residual import ResidualTracker, exposure_residual
from edi_live.edi.residual_schedule import ResidualCarry, residual_changes
from edi_live.edi.selection import select, time_index, window


REFERENCE_MASS = 1.0  # A: a reference frame's own error, in units of event mass (log intensity)
TIME_STEPS = 4
RESIDUAL_SPAN = 0.3  # the residual a reference holds: its estimate averaged over this share of the interval


def time_share(tau: float, steps: int = TIME_STEPS) -> float:
    """tau in `steps` steps of values 0, 1/(steps-1), ..., 1 (the first step 0 and the last 1, so that the fused
    video runs continuously into each deblurred frame); 0 at tau <= 0 or NaN, 1 at tau >= 1."""
    if not tau > 0.0:
        return 0.0
    if tau >= 1.0:
        return 1.0
    return min(int(tau * steps), steps - 1) / (steps - 1)


def fusion_weights(mass_crossed: np.ndarray, mass_total: np.ndarray, tau: float, informative0: np.ndarray,
                   informative1: np.ndarray, *, reference_mass: float = REFERENCE_MASS) -> tuple[np.ndarray, np.ndarray]:
    """(forward weight, backward weight), float32 arrays of the inputs' shape, finite, in [0, 1], summing to one.

    `mass_crossed`/`mass_total`: event mass c_on n_on + c_off n_off from f_k to t and over (f_k, f_{k+1}] per
    pixel; `tau` = (t - f_k) / (f_{k+1} - f_k); `informative0/1`: where frame k / k+1 is neither clipped nor black."""
    total = np.clip(np.nan_to_num(np.asarray(mass_total, np.float64), posinf=0.0), 0.0, None)
    crossed = np.minimum(np.clip(np.nan_to_num(np.asarray(mass_crossed, np.float64), posinf=0.0), 0.0, None), total)
    inf0, inf1 = np.asarray(informative0, bool), np.asarray(informative1, bool)
    tq = time_share(tau)
    if tq in (0.0, 1.0):
        wb = np.full(total.shape, tq)
    else:
        a = float(reference_mass)
        wb = (crossed + a * tq) / (total + a)
        wb = np.where(inf0 & ~inf1, 0.0, np.where(inf1 & ~inf0, 1.0, wb))
    wb = np.clip(wb, 0.0, 1.0).astype(np.float32)
    return (np.float32(1.0) - wb), wb


def fused_log(forward: np.ndarray, backward: np.ndarray, w_backward: np.ndarray) -> np.ndarray:
    """(1 - w) F + w Bk as F + w (Bk - F), float32, clipped to the log-state bounds."""
    f = np.asarray(forward, np.float32)
    out = f + np.asarray(w_backward, np.float32) * (np.asarray(backward, np.float32) - f)
    return np.clip(out, LOG_MIN, LOG_MAX).astype(np.float32)


def event_mass(events: np.ndarray, width: int, height: int, c_on: float, c_off: float, *, t0: int | None = None,
               t1: int | None = None, mask: np.ndarray | None = None) -> np.ndarray:
    """c_on n_on + c_off n_off per pixel for events with t0 <= t <= t1, (H, W) float64."""
    idx, _, p = select(events, width, height, t0, t1, mask)
    w = np.where(p, np.float64(c_on), np.float64(c_off))
    return np.bincount(idx, weights=w, minlength=width * height).reshape(height, width)


@dataclass(frozen=True)
class FusionPlan:
    """What the fused frames between f0 and f1 need: the log image just after f0 without the time term, each
    pixel's log change per ON and per OFF event (flat float32, the OFF one negative), and the time term's
    amplitude K (flat float32: the time term is tau_q K)."""

    f0_us: int
    f1_us: int
    start: np.ndarray  # (H, W) float32
    step_on: np.ndarray
    step_off: np.ndarray
    time_term: np.ndarray
    start_u8: np.ndarray | None = None  # to_uint8(start), when the plan's kernel made it


def fusion_plan(log_ref0: np.ndarray, log_ref1: np.ndarray, events: np.ndarray, f0_us: int, f1_us: int,
                c_on: float, c_off: float, informative0: np.ndarray, informative1: np.ndarray, *,
                mask: np.ndarray | None = None, reference_mass: float = REFERENCE_MASS) -> FusionPlan:
    """The plan of the fused frames in (f0, f1) from the two references and the events between them (the events
    with f0 < t <= f1 are used; masked pixels' events are ignored, as in the references' own propagation)."""
    h, w = log_ref0.shape
    e01, mass = _pair_sums(events, w, h, c_on, c_off, f0_us, f1_us, mask)
    a = float(reference_mass)
    if _backend.have_numba():  # one pass over the pixels, no full-frame temporaries
        flat = lambda v, dt: np.ascontiguousarray(v, dt).reshape(-1)  # noqa: E731
        start, start_u8 = np.empty((h, w), np.float32), np.empty((h, w), np.uint8)
        step_on, step_off, term = (np.empty(h * w, np.float32) for _ in range(3))
        _kernels_fused.plan_pixels(flat(log_ref0, np.float32), flat(log_ref1, np.float32), e01.reshape(-1),
                                   mass.reshape(-1), flat(informative0, bool), flat(informative1, bool),
                                   np.float32(a), np.float32(c_on), np.float32(c_off), np.float32(LOG_MIN),
                                   np.float32(LOG_MAX), start.reshape(-1), step_on, step_off, term,
                                   start_u8.reshape(-1), *render_buckets())
        return FusionPlan(int(f0_us), int(f1_us), start, step_on, step_off, term, start_u8)
    r0 = np.asarray(log_ref0, np.float32)
    d = np.asarray(log_ref1, np.float32) - r0 - e01
    inf0, inf1 = np.asarray(informative0, bool), np.asarray(informative1, bool)
    one_sided = inf0 != inf1
    share = d / (mass + np.float32(a))
    share[one_sided] = 0.0
    start = r0.copy()
    only1 = inf1 & ~inf0  # the one-sided pixels take frame k+1 whole (frame k's only: weight 0, nothing to add)
    start[only1] += d[only1]
    np.clip(start, LOG_MIN, LOG_MAX, out=start)
    share = share.reshape(-1)
    step_on = np.float32(c_on) * (np.float32(1.0) + share)
    step_off = np.float32(-c_off) * (np.float32(1.0) - share)
    return FusionPlan(int(f0_us), int(f1_us), start, step_on, step_off, np.float32(a) * share)


def forward_plan(log_ref: np.ndarray, f_us: int, c_on: float, c_off: float) -> FusionPlan:
    """The plan of plain forward EDI from one reference (no later frame yet: the frames after the last one): every
    pixel steps by c_on / -c_off per event, no time term."""
    n = log_ref.size
    start = np.clip(np.asarray(log_ref, np.float32), LOG_MIN, LOG_MAX)
    return FusionPlan(int(f_us), int(f_us), start, np.full(n, c_on, np.float32), np.full(n, -c_off, np.float32),
                      np.zeros(n, np.float32))


def _pair_sums(events: np.ndarray, w: int, h: int, c_on: float, c_off: float, f0_us: int, f1_us: int,
               mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(E(f0 -> f1), event mass over (f0, f1]) per pixel, (H, W) float32."""
    if _backend.have_numba():
        ev = window(events, int(f0_us) + 1, int(f1_us))
        m, use_m = _backend.mask_arg(mask)
        delta, mass = np.zeros(w * h, np.float32), np.zeros(w * h, np.float32)
        _kernels_fused.pair_sums(ev["x"], ev["y"], ev["p"], w, h, m, use_m, np.float32(c_on), np.float32(c_off),
                                 delta, mass)
        return delta.reshape(h, w), mass.reshape(h, w)
    e01 = event_delta(events, w, h, c_on, c_off, t0=f0_us + 1, t1=f1_us, mask=mask)
    mass = event_mass(events, w, h, c_on, c_off, t0=f0_us + 1, t1=f1_us, mask=mask).astype(np.float32)
    return e01, mass


class FusedPropagator:
    """The fused log image and its uint8 display, advanced event by event from f0 (events after f0, in order)."""

    def __init__(self, plan: FusionPlan, mask: np.ndarray | None) -> None:
        self.plan = plan
        self.log_image = plan.start.copy()
        self.display = to_uint8(self.log_image) if plan.start_u8 is None else plan.start_u8.copy()
        self.tau_q = 0.0
        self._h, self._w = self.log_image.shape
        self._mask = mask
        self._m, self._use_m = _backend.mask_arg(mask)

    def set_time(self, tau_q: float) -> None:
        """Move the time term to tau_q (a value of time_share): one pass over the pixels when it changes."""
        if tau_q == self.tau_q:
            return
        flat = self.log_image.reshape(-1)
        if _backend.have_numba():  # only the pixels with a time term; the display updated in the same pass
            _kernels_fused.shift_time(flat, self.plan.time_term, np.float32(tau_q - self.tau_q),
                                      np.float32(LOG_MIN), np.float32(LOG_MAX), self.display.reshape(-1),
                                      *render_buckets())
            self.tau_q = tau_q
            return
        flat += np.float32(tau_q - self.tau_q) * self.plan.time_term
        np.clip(flat, LOG_MIN, LOG_MAX, out=flat)
        self.display = to_uint8(self.log_image)
        self.tau_q = tau_q

    def apply(self, events: np.ndarray) -> None:
        flat, disp = self.log_image.reshape(-1), self.display.reshape(-1)
        if _backend.have_numba():
            ev = window(events, None, None)
            _kernels_fused.propagate_steps(ev["x"], ev["y"], ev["p"], self._w, self._h, self._m, self._use_m, flat,
                                           self.plan.step_on, self.plan.step_off, LOG_MIN, LOG_MAX, disp,
                                           *render_buckets())
            return
        idx, _, p = select(events, self._w, self._h, None, None, self._mask)
        if idx.size == 0:
            return
        steps = np.where(p, self.plan.step_on[idx], self.plan.step_off[idx]).astype(np.float64)
        flat += np.bincount(idx, weights=steps, minlength=flat.size).astype(np.float32)
        flat[idx] = np.clip(flat[idx], LOG_MIN, LOG_MAX)
        disp[idx] = to_uint8(flat[idx])


def fused_frames(current: tuple[np.ndarray, int], previous: tuple[np.ndarray, int] | None,
                 informative: tuple[np.ndarray, np.ndarray] | None, times: Sequence[int], events: np.ndarray,
                 c: tuple[float, float], mask: np.ndarray | None, *, residual: bool = True,
                 carry: ResidualCarry | None = None) -> list[tuple[np.ndarray, int, int]]:
    """The latent images at `times` (ascending) in one propagation pass over the events: (uint8 image, t, events
    since the previous image) per time. `current`/`previous`: (log L(f), f) of the two references (previous None:
    plain forward EDI, for times after the current f); `informative`: where the previous / current APS frame is
    neither clipped nor black; `events`: at least those from the earlier reference to the last time (with
    `residual`, the sub-threshold residual estimate between events: residual_schedule.COLD_CONTEXT intervals before
    f0 to the new frame's exposure end, or from just after carry.snap_us when `carry`, what the previous pair left,
    is warm for this pair: see edi_live.edi.residual_schedule)."""
    if previous is not None and residual and _backend.have_numba():
        return _residual_frames(current, previous, informative, times, events, c, mask, carry)
    log1, f1 = current
    tracker = None
    if previous is not None and not residual:
        log0, f0 = previous
        plan = fusion_plan(log0, log1, events, f0, f1, c[0], c[1], informative[0], informative[1], mask=mask)
    elif previous is None:
        log0, f0 = log1, f1
        plan = forward_plan(log1, f1, *c)
    else:
        log0, f0 = previous
        h, w = log0.shape
        span = int(RESIDUAL_SPAN * (f1 - f0))
        tracker = ResidualTracker(events, w, h, c[0], c[1], mask, start_us=f0 - span - 1)
        held0 = exposure_residual(tracker, f0 - span, f0 + span).reshape(h, w)
        held1 = exposure_residual(tracker, f1 - span, f1 + span).reshape(h, w)
        tracker.restart()
        plan = fusion_plan(log0 - held0, log1 - held1, events, f0, f1, c[0], c[1], informative[0], informative[1],
                           mask=mask)
    prop = FusedPropagator(plan, mask)
    t = events["t"]
    pos = time_index(t, f0, "right")
    out = []
    for t_us in map(int, times):
        if t_us <= f0 or (previous is not None and t_us >= f1):  # the video passes through the deblurred frames
            out.append((to_uint8(log1 if t_us >= f1 else log0), t_us, 0))
            continue
        end = time_index(t, t_us, "right")
        prop.apply(events[pos:end])
        if previous is not None:
            prop.set_time(time_share((t_us - f0) / (f1 - f0)))
        if tracker is not None:
            tracker.at_painted(t_us, residual_seen(t_us, span), prop.log_image, prop.display)
        out.append((prop.display.copy(), t_us, max(0, end - pos)))
        pos = max(pos, end)
    return out


def _residual_frames(current: tuple[np.ndarray, int], previous: tuple[np.ndarray, int],
                     informative: tuple[np.ndarray, np.ndarray], times: Sequence[int], events: np.ndarray,
                     c: tuple[float, float], mask: np.ndarray | None,
                     carry: ResidualCarry | None) -> list[tuple[np.ndarray, int, int]]:
    """fused_frames between two references with the residual estimate, with the kernels: the frames inside the
    pair in one call, the estimate from its schedule of changes (the same images as the per-frame path)."""
    (log1, f1), (log0, f0) = current, previous
    h, w = log0.shape
    times = [int(t) for t in times]
    inside = np.array([t for t in times if f0 < t < f1], np.int64)
    n = inside.size
    span = int(RESIDUAL_SPAN * (f1 - f0))
    ch = residual_changes(events, w, h, c, mask, f0, f1, span, inside, carry)
    ref0, ref1, res = log0 - ch.held0, log1 - ch.held1, ch.start.copy()
    plan = fusion_plan(ref0, ref1, events, f0, f1, c[0], c[1], informative[0], informative[1], mask=mask)
    dtau, before = np.zeros(n, np.float32), 0.0
    for j, t_us in enumerate(inside.tolist()):
        tau_q = time_share((t_us - f0) / (f1 - f0))
        if tau_q != before:
            dtau[j], before = np.float32(tau_q - before), tau_q
    out = np.empty((n, h * w), np.uint8)
    t = events["t"]
    pos = time_index(t, f0, "right")
    m, use_m = _backend.mask_arg(mask)
    _kernels_fused.render_frames(events["x"], events["y"], events["p"], t, pos, w, h, m, use_m, inside, dtau,
                                 plan.start.reshape(-1).copy(), plan.step_on, plan.step_off, plan.time_term,
                                 res, plan.start_u8.reshape(-1).copy(), bool(res.any()), ch.offsets, ch.q, ch.v,
                                 np.float32(LOG_MIN), np.float32(LOG_MAX), out, *render_buckets())
    ends = [time_index(t, t_us, "right") for t_us in inside.tolist()]  # np.searchsorted would copy the strided t
    counts = np.diff(np.array(ends, np.int64), prepend=pos)
    result, j = [], 0
    for t_us in times:
        if f0 < t_us < f1:
            result.append((out[j].reshape(h, w), t_us, max(0, int(counts[j]))))
            j += 1
        else:  # the video passes through the deblurred frames
            result.append((to_uint8(log1 if t_us >= f1 else log0), t_us, 0))
    return result


def residual_seen(t_us: int, span: int) -> tuple[int, int]:
    """The events a fused frame's residual estimate at t uses: from 10 spans before t (a pixel's last event, long
    ago where it is still) to one span after (what the next APS frame's exposure brought): the same estimate from
    either pair of frames around a reference, so nothing jumps where the pair changes."""
    return t_us - 10 * span, t_us + span
