"""The EDI worker thread: reads the ring in order and turns APS frames and events into sharp frames.

Accepts an `EventRing` (events in time order, each APS frame queued just past its exposure end) and a
`Reconstructor`; hands each `Reconstruction` to the sinks as it is made (t increases, except that in causal mode
a deblurred frame at f follows the latent frames to its exposure end, and any made while the helper thread
deblurred it). Times are µs on the sensor clock; host times (latency, --max-fps, the heartbeat while no event
comes) are time.monotonic. Without --max-fps and the deblur thread, the frames depend on the event stream only,
not on how the reads cut it (a replay is repeatable). The policy, in full in docs/node.md:
- an APS frame is deblurred once its exposure's events (event clock: frame_gate) are read; then a latent frame
  every `every` events or `every_ms` of sensor time (frame_cadence), at most `max_fps` per second;
- noise-only events (edi_live.activity) move the latent image but make no frame, an onset makes one at its first
  event; a still scene is deblurred, and a heartbeat sent, once per `heartbeat_s` of sensor time (still_frames);
- "nearest" renders latent times past the midpoint from the next APS frame (nearest_mode); a gap pauses them;
- deblur_thread: APS frames deblurred on a helper thread that sends them, a copy streams meanwhile (deblur_handover).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from edi_live.activity import StaticScene
from edi_live.config import EdiConfig
from edi_live.datatypes import Frame, Reconstruction
from edi_live.deblur_handover import DeblurThread, PendingDeblur
from edi_live import held_frames
from edi_live.frame_cadence import FrameCadence, frame_cadence_us
from edi_live.frame_demand import FrameDemand
from edi_live.frame_gate import FrameGate, in_event_clock
from edi_live.fused_mode import FusedHoldBack
from edi_live.nearest_mode import NearestHoldBack
from edi_live.quality import PredictionScore
from edi_live.quiet_reads import QuietReads
from edi_live.reconstruction import Reconstructor
from edi_live.ring import EventChunk, EventRing, FrameEntry
from edi_live.still_frames import StillFrames
from edi_live.worker_stats import worker_stats

if TYPE_CHECKING:
    from edi_live.pixel_noise import NoiseRates

log = logging.getLogger(__name__)

Sink = Callable[[Reconstruction], None]
_T_MAX = np.iinfo(np.int64).max
_CHUNK_EVENTS = 1 << 16  # events taken from the ring per lock (then split into every-N slices locally)
_BATCH_FRAMES = 32  # latent frames made per reconstructor call (bounds the images held before sending)
_IDLE_WAIT_S = 0.25
_ABORT_DEBLUR_WAIT_S = 1.0  # aborted with a deblur pending: how long to wait for it (one on_frame + settle)


class EdiWorker:
    """Runs the reconstructor on its own thread ("edi-worker"); see the module docstring for the policy."""

    def __init__(self, ring: EventRing, reconstructor: Reconstructor, config: EdiConfig, sinks: Sequence[Sink] = (), *,
                 on_error: Callable[[BaseException], None] | None = None, name: str = "edi-worker",
                 frames_wanted: Callable[[], bool] | None = None) -> None:
        self.demand = FrameDemand(frames_wanted)  # latent frames nobody would receive are not rendered
        self.ring, self.rec, self.config = ring, reconstructor, config
        reconstructor.follow_latent = config.mode != "fused"  # fused frames come from both references
        self.sinks = list(sinks)
        self._sinks_lock = threading.Lock()  # the deblur thread hands its frames to the sinks itself
        self._sinks_open = True
        self.name = name
        self._on_error = on_error
        self._thread: threading.Thread | None = None
        self._abort = threading.Event()
        self.done = threading.Event()
        self.error: BaseException | None = None
        # everything below is touched only by the worker thread (stats readers see plain ints)
        self._since = 0  # events since the last sent frame
        self._cadence = FrameCadence(config.every, frame_cadence_us(config.every_ms))  # ... and its sensor time
        self._await_reference = False  # after a gap: no latent frames until the next APS frame
        self._last_emit_s = 0.0
        self._last_arrival_ns = 0
        self._ref_f_us: int | None = None
        self._nearest = FusedHoldBack() if config.mode == "fused" else NearestHoldBack()  # latent times held back
        self._gate = FrameGate()  # whether an APS frame's late events are in
        self._deblur_ms: collections.deque[float] = collections.deque(maxlen=256)  # on_frame wall time
        self._pending: PendingDeblur | None = None  # causal mode with deblur_thread, run by _helper
        self._helper = DeblurThread(wake=ring.poke, deliver=self._to_sinks)
        self._scene = StaticScene()  # events that show only background noise make no frames
        self._quiet = QuietReads(config.every)  # ... nor wake-ups per packet (read in larger steps)
        # how well the output predicted each APS frame (scored on this thread; stats() reads a copy)
        self.quality = (PredictionScore(config.mode, score_every=config.quality_every,
                                        color_filter=config.color_filter, gray=config.gray)  # type: ignore[arg-type]
                        if config.quality_every else None)
        self.events_in = self.frames_in = self.heartbeats = self.skipped_static = self.skipped_max_fps = self.gaps = 0
        self.sent = {"deblurred": 0, "latent": 0}
        self.skipped_static_deblur = 0  # APS frames not deblurred at all (static scene)
        self._still = StillFrames(config.every, config.heartbeat_s)  # what a still scene skips (sensor clock)
        self._last_read_s = 0.0  # host time of the latest read with events
        self.wakeups = 0  # idle waits: bounded by ~4/s plus data arrivals (no busy loop)
        self.busy_s = self.cpu_s = 0.0

    # ---------------------------------------------------------------- control (any thread)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def abort(self) -> None:
        """Stop soon without draining the ring (after a fault downstream, or when draining takes too long)."""
        self._abort.set()

    def join(self, timeout_s: float) -> bool:
        """True if the thread ended within timeout_s."""
        if self._thread is not None:
            self._thread.join(timeout_s)
        return self._thread is None or not self._thread.is_alive()

    # ---------------------------------------------------------------- the worker thread

    def _run(self) -> None:
        cpu0 = time.thread_time()
        try:
            self._last_emit_s = self._last_read_s = time.monotonic()
            while not self._abort.is_set():
                version = self.ring.version
                if self._step():
                    continue
                if self.ring.exhausted and self._pending is None:
                    break
                self._heartbeat()
                self.wakeups += 1
                self.ring.wait(version, self._idle_wait_s(),
                               self._quiet.wake(self.ring, self._scene.quiet, self._gate.held_through))
            if not self._abort.is_set():
                self._adopt(wait=True)  # a deblur still pending, if any
                self._release_held()
                if self.quality is not None:
                    self.quality.finish()
            elif self._pending is not None and self._pending.done.wait(_ABORT_DEBLUR_WAIT_S):
                self._adopt(wait=False)  # the stats and a saved calibration then read the master
        except BaseException as exc:
            self.error = exc
            log.debug("worker failed", exc_info=True)
            if self._on_error is not None:
                self._on_error(exc)
        finally:
            with self._sinks_lock:
                self._sinks_open = False  # the node closes the sinks next: a deblur still running sends nothing
            self._helper.close()
            self.cpu_s = time.thread_time() - cpu0
            self.done.set()

    def _idle_wait_s(self) -> float:
        due = max(self._last_emit_s, self._last_read_s) + self.config.heartbeat_s - time.monotonic()
        return max(0.001, min(_IDLE_WAIT_S, due))

    def _step(self) -> bool:
        """Handle one APS frame or one chunk of events. False if there was nothing to do."""
        if self._pending is not None and self._pending.done.is_set():
            self._adopt(wait=False)
            return True
        if self._pending is not None and self._pending.claim_result():  # sent before the master settles
            self._send_deblurred(self._pending)
            return True
        entry = self.ring.peek_frame()
        limit, through = (entry.end_index if entry is not None else None), None
        if entry is not None and self.ring.read_index >= entry.end_index:
            if self._pending is not None:
                return False  # the original's settle() may move the clock offset: gate with it (its end pokes)
            done = self.ring.closed and not self.ring.unread_events
            if self._gate.ready(entry.frame, self.rec.clock_offset_us, done):
                self.ring.pop_frame()
                self._on_frame(entry)
                return True
            # its (late) event-clock window's events are still to come: read just through them, not past
            limit, through = None, self._gate.held_through
        elif entry is not None and self._scene.quiet and self._pending is None and self.rec.clock_offset_us > 0:
            limit, through = None, entry.frame.exposure_end_us + self.rec.clock_offset_us  # and its late window
        if not self.ring.unread_events or (entry is None and self._scene.quiet and self._quiet.defer(self.ring)):
            return False  # (a push after this look changes the version the wait compares with)
        chunk = self.ring.read_events(_CHUNK_EVENTS, limit, through)
        if len(chunk.events) == 0:
            return False
        self._on_chunk(chunk)
        return True

    def _on_chunk(self, chunk: EventChunk) -> None:
        n = len(chunk.events)
        self.events_in += n
        self._last_read_s = time.monotonic()
        self._gate.events_read(int(chunk.events["t"][-1]))
        if self.quality is not None:
            self.quality.on_events(chunk.events)
        self._last_arrival_ns = chunk.arrival_ns_at(n)
        if self._pending is not None and chunk.gap:
            self._pending.gap = True  # the streamer logs no more calls; the master hears of the gap when adopted
        if chunk.gap:
            self.gaps += 1
            self._await_reference = True
            self._nearest.gap()
            self.rec.mark_gap()  # lets the c estimator skip pairs across the gap
        if self._await_reference or not self.rec.has_reference:
            self._since += n
            return  # nothing to update before the first (or next, after a gap) APS frame
        t0 = time.perf_counter()
        for lo, hi, state in self._scene.segments(chunk.events):  # cut where the stream's state changes
            if state == "onset":
                self._since = max(self._since, self.config.every - 1)  # a frame at its first event
            self._in_event_clock(chunk, lo, hi, state)
        self.busy_s += time.perf_counter() - t0

    def _in_event_clock(self, chunk: EventChunk, lo: int, hi: int, state: str) -> None:
        """Events [lo, hi) of the chunk, and a heartbeat frame at the first event heartbeat_s of sensor time
        after the latest frame sent. Noise moves the latent image but makes no frame; events the activity test
        only holds active make frames by count alone (edi_live.activity)."""
        t = chunk.events["t"]
        while lo < hi:
            k = self._still.heartbeat_at(t, lo, hi)
            end = min(hi, k + 1)
            if state == "noise":
                self.rec.on_events(chunk.events[lo:end], chunk.arrival_ns_at(end))
                self._since = 0
            else:
                self._stream(chunk, lo, end, timed=state != "held")
            if k < hi and self._still.heartbeat_due(int(t[k])):
                self._heartbeat_at(int(t[k]))
            lo = end

    def _stream(self, chunk: EventChunk, lo: int, hi: int, timed: bool = True) -> None:
        """Events [lo, hi) of an active scene: a latent frame every `every` events."""
        events, n, every = chunk.events[lo:hi], hi - lo, self.config.every
        if self._cadence.every_us:  # (by count only, the still-scene decisions stay those of the count rule)
            self._still.streamed(n)
        if self.config.max_fps is None and self.config.mode == "causal":  # batches: no frame is held back
            # up to _BATCH_FRAMES frames per call (the loop's frames); a 64k-event chunk at --every 1: 64k images
            cuts, tail = self._cadence.cuts(events["t"], self._since, timed)
            if self.demand.skip(len(cuts), self.quality):
                cuts = cuts[:0]  # the events below still move the latent image
            pos = 0
            for g in range(0, len(cuts), _BATCH_FRAMES):
                if self._abort.is_set():  # one read at --every 1 is 64k frames: abort between batches
                    return
                group = cuts[g:g + _BATCH_FRAMES]
                end = group[-1]
                recs = self.rec.on_events_frames(events[pos:end], [c - pos for c in group],
                                                 [chunk.arrival_ns_at(lo + c) for c in group])
                pos = end
                for rec in recs:
                    self._emit(rec, asked=True)
            if pos < n:
                self.rec.on_events(events[pos:], chunk.arrival_ns_at(hi))
            self._since = tail
            return
        pos, t = 0, events["t"]
        while pos < n and not self._abort.is_set():
            take = self._cadence.take(t[pos:], self._since, timed)
            part = events[pos:pos + take]
            pos += take
            self._since += take
            arrival = chunk.arrival_ns_at(lo + pos)
            self.rec.on_events(part, arrival)
            if self._since >= every or timed and self._cadence.due(int(t[pos - 1])):
                self._latent_due(int(t[pos - 1]), arrival)

    def _latent_due(self, t_us: int, arrival_ns: int) -> None:
        now = time.monotonic()
        self._since = 0
        self._cadence.made(t_us)
        if self.config.max_fps is not None and now - self._last_emit_s < 1.0 / self.config.max_fps:
            self.skipped_max_fps += 1
            return
        if self.config.mode != "causal" and self._nearest.should_hold(t_us, self._ref_f_us):
            self._nearest.held.append((t_us, arrival_ns))
            self._still.emitted(t_us)  # on its way: no heartbeat for it (it would overtake the held frames)
            return
        self._release_held()  # past the hold's cap
        self._emit(self.rec.render())

    def _on_frame(self, entry: FrameEntry) -> None:
        self.frames_in += 1
        self._quiet.on_aps_frame(entry.frame, self.rec.clock_offset_us)
        threaded = self._use_deblur_thread()  # no deblur is pending here: _step waits until it is adopted
        aps = in_event_clock(entry.frame, self.rec.clock_offset_us)
        if self.quality is not None and not threaded:
            self.quality.on_aps_frame(aps)
        self._deblur(entry, aps)
        if self.quality is not None and threaded:  # once the deblur is under way: it need not wait (~0.2 ms)
            self.quality.on_aps_frame(aps)

    def _deblur(self, entry: FrameEntry, in_event_clock_frame: Frame) -> None:
        frame = entry.frame
        t0 = time.perf_counter()
        # exposure start (in the event clock: clock_offset_us later) .. read cursor
        events = self.ring.window(frame.exposure_start_us + self.rec.clock_offset_us, _T_MAX)
        if self.rec.has_reference and not self._await_reference and self._still.skip_deblur(
                frame, len(events), self._since, self._scene, events_seen=self.events_in > 0):
            self.skipped_static_deblur += 1
            return
        self._scene.new_reference(in_event_clock_frame, anchor=self._await_reference)
        self._still.deblurred(frame)
        f_us = frame.mid_exposure_us + self.rec.clock_offset_us
        arrival = max(entry.arrival_ns, self._last_arrival_ns)
        if self._use_deblur_thread():
            send = self._still.moving(len(events), self._since, self._scene, self.events_in > 0)
            self._since = 0 if send else self._since  # latent frames count from here, as when sent inline
            self._pending = PendingDeblur(self.rec, entry, events, arrival, send, self._helper)
            self.rec = self._pending.streamer  # streams from the previous reference; its calls are replayed later
            self.busy_s += time.perf_counter() - t0
            return
        out = held_frames.before_new_reference(self.rec, self.ring, self._nearest, self._ref_f_us, f_us)
        first = not self.rec.has_reference
        t_deblur = time.perf_counter()
        deblurred = self.rec.on_frame(frame, events, arrival)
        self._deblur_ms.append((time.perf_counter() - t_deblur) * 1e3)
        self._nearest.new_reference(self._ref_f_us, f_us)
        self._ref_f_us = f_us
        self._await_reference = False
        out += held_frames.after_new_reference(self.rec, self.ring, self._nearest, f_us, frame,
                                               self.config.mode == "fused")
        if first or out or self._still.moving(len(events), self._since, self._scene, self.events_in > 0):
            out.append(deblurred)
        else:
            self.skipped_static += 1
        self.busy_s += time.perf_counter() - t0
        for rec in sorted(out, key=lambda r: r.t_us):
            self._emit(rec)
        t0 = time.perf_counter()
        self.rec.settle()  # the calibration work the deblurred frame did not wait for
        self.busy_s += time.perf_counter() - t0

    def _use_deblur_thread(self) -> bool:
        return bool(self.config.deblur_thread and self.config.mode == "causal" and self.rec.has_reference
                    and not self._await_reference)

    def _adopt(self, wait: bool) -> None:
        """Make the master (with the new reference) the streaming reconstructor again; count the frame it sent."""
        pending = self._pending
        if pending is None or (not wait and not pending.done.is_set()):
            return
        while not pending.done.wait(0.1):
            if self._abort.is_set():
                return
        self._pending = None
        t0 = time.perf_counter()
        self.rec = pending.adopt()  # raises the helper thread's error, if any
        self._deblur_ms.append(pending.deblur_ms)
        self._ref_f_us = pending.result.t_us if pending.result is not None else self._ref_f_us  # f, event clock
        self._await_reference |= pending.gap  # the catch-up spans lost data: wait for the next APS frame
        self.busy_s += time.perf_counter() - t0
        if pending.claim_result():  # not counted yet: the deblur ended just now
            self._send_deblurred(pending)

    def _send_deblurred(self, pending: PendingDeblur) -> None:
        """Count the helper thread's frame: it gave the frame to the sinks itself (_to_sinks) once it was ready."""
        if pending.send and pending.result is not None:
            self._count_emitted(pending.result)  # not _since: latent frames count from the hand-over
        else:
            self.skipped_static += 1

    def _heartbeat(self) -> None:
        """The host-clock heartbeat, for when no event came for heartbeat_s (no sensor time passes to make one)."""
        if self.rec.has_reference and not self._await_reference and \
                time.monotonic() - max(self._last_emit_s, self._last_read_s) >= self.config.heartbeat_s:
            self._heartbeat_at(None)

    def _heartbeat_at(self, t_us: int | None) -> None:
        """A heartbeat frame after the held latent times; at sensor time t_us only if none of them was at t_us
        (None: the host-clock heartbeat, sent in any case)."""
        self._release_held()
        if t_us is None or self._still.heartbeat_due(t_us):
            self.heartbeats += 1
            self._emit(self.rec.render())

    def _release_held(self) -> None:
        """Held latent times (nearest, fused) from the current reference, before any later frame and at the end."""
        for rec in held_frames.render_rest(self.rec, self.ring, self._nearest, self._ref_f_us):
            self._emit(rec)

    def _emit(self, rec: Reconstruction, asked: bool = False) -> None:
        self._since = 0
        if rec.kind == "latent":  # (a deblurred frame shows f: the latent frames' time rule goes on)
            self._cadence.made(rec.t_us)
        self._count_emitted(rec, asked)
        self._to_sinks(rec)

    def _to_sinks(self, rec: Reconstruction) -> None:
        """Also the helper thread's, with its frame the moment it is ready (a hop to this thread cost ~0.5 ms)."""
        with self._sinks_lock:
            for sink in self.sinks if self._sinks_open else ():
                sink(rec)

    def _count_emitted(self, rec: Reconstruction, asked: bool = False) -> None:
        self._last_emit_s = time.monotonic()
        self._still.emitted(rec.t_us)
        self.sent[rec.kind] = self.sent.get(rec.kind, 0) + 1
        if self.quality is not None:
            self.demand.score(rec, self.quality, asked)

    # ---------------------------------------------------------------- stats (any thread)

    def stats(self) -> dict[str, Any]:
        return worker_stats(self)  # its own module: this one stays under 400 lines

    def noise_rates(self) -> NoiseRates | None:
        """The rates to save with a calibration; None while a deblur is pending after an abort (being written)."""
        return self.rec.noise_rates() if self._pending is None else None
