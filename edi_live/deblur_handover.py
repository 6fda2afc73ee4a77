"""Deblurring an APS frame off the worker thread: while the original reconstructor computes the new reference on
the "edi-deblur" helper thread, the worker streams latent frames from a streaming copy that still holds the
previous reference. The deblurred frame goes to the sinks (`deliver`, from the helper thread) as soon as on_frame has
it (`ready`: on_frame's callback, before it readies its state for the events after the frame), and the worker counts
it when it sees it ready (`claim_result`); the helper thread then finishes on_frame,
runs the reconstructor's settle() (the calibration work the frame did not wait for), replays into the original
the calls the copy was given meanwhile (its catch-up), and only then (`done`) may the worker adopt the original
again, replaying the few calls logged since.

The replay repeats those calls one by one (the same pieces, arrival stamps and renders, in order), not their
events in one batch: the original decides some things per call, before it applies the call's events (a pixel the
flicker detector flags in a piece is masked for the whole piece), and the counts it keeps then feed the
unreliable-pixel test and the c, black-level and noise estimates. Replayed call by call, it ends in the state
the inline path (no helper thread) gives, and so makes the same frames.
"""

from __future__ import annotations

import functools
import inspect
import queue
import threading
import time
from typing import Any, Callable, Sequence

import numpy as np

from edi_live.datatypes import Reconstruction
from edi_live.reconstruction import Reconstructor
from edi_live.ring import FrameEntry


_CATCH_UP_ROUNDS = 4  # replaying is faster than streaming (nothing rendered): each round's backlog is shorter


class PendingDeblur:
    """One APS frame being deblurred on the "edi-deblur" helper thread by the master reconstructor, while the
    worker streams latent frames from `streamer`, the master's streaming copy as of now (made before the deblur
    starts), which still holds the previous reference. The calls the streamer gets meanwhile are logged and
    replayed into the master when it is adopted."""

    def __init__(self, master: Reconstructor, entry: FrameEntry, events: np.ndarray, arrival_ns: int, send: bool,
                 helper: DeblurThread) -> None:
        self.master, self.entry, self.send = master, entry, send
        self._wake, self._deliver = helper.wake, helper.deliver
        self.calls: list[tuple] = []  # (events, arrival_ns, cuts, arrivals) per on_events(_frames); () per render
        self.replayed = 0  # calls[:replayed] are in the master already (the helper thread's catch-up)
        self.gap = False  # data were lost meanwhile: the streamer logs nothing more, the master is told at adopt
        self.streamer = StreamingCopy(master.streaming_copy(), self)
        self.result: Reconstruction | None = None
        self.error: BaseException | None = None
        self.deblur_ms = self.settle_ms = 0.0
        self.ready = threading.Event()  # the frame (or an error) is out; on_frame and settle() may still run
        self.done = threading.Event()  # settle() returned too: the master may be adopted
        self._claimed = False
        helper.run(functools.partial(self._run, events, arrival_ns))

    def claim_result(self) -> bool:
        """True at most once, when the deblurred frame is ready and no error was seen yet: the worker counts it as
        sent (`deliver` sent it) or skipped then. An error raised by on_frame after its `ready` call is still
        reported at adopt(), after the frame went out. Worker thread only."""
        if self._claimed or not self.ready.is_set() or self.error is not None:
            return False
        self._claimed = True
        return True

    def adopt(self) -> Reconstructor:
        """Once `done`: the master, with the calls the streamer was given meanwhile replayed into it (and then the
        gap the worker saw, if any). Raises the helper thread's error, if there was one. The frames the replayed
        calls render are dropped (the streamer's went out instead): replay_frames leaves the state on_events_frames
        leaves without having to render them."""
        if self.error is not None:
            raise self.error
        self._replay(len(self.calls))
        self.calls = []
        if self.gap:
            self.master.mark_gap()
        return self.master

    def _replay(self, end: int) -> None:
        master, calls = self.master, self.calls
        while self.replayed < end:
            call = calls[self.replayed]
            if not call:
                master.render()
            elif call[2] is None:
                master.on_events(call[0], call[1])
            else:
                master.replay_frames(call[0], call[2], call[3])
            self.replayed += 1

    def _catch_up(self) -> None:
        """Helper thread, before `done`: replay the calls logged so far, and those logged meanwhile, a few rounds,
        so that adopt() on the worker thread has only the last few left (replaying a 40 ms deblur's calls there
        held the latent frames behind it for ~4 ms). The worker only appends to `calls` until `done`."""
        for _ in range(_CATCH_UP_ROUNDS):
            end = len(self.calls)
            if self.replayed >= end:
                return
            self._replay(end)

    def _run(self, events: np.ndarray, arrival_ns: int) -> None:
        t0 = time.perf_counter()

        def frame_ready(result: Reconstruction) -> None:  # inside on_frame: the frame is complete, its state not
            self.result = result
            self.deblur_ms = (time.perf_counter() - t0) * 1e3
            if self.send:
                self._deliver(result)  # sent from here, now; the worker counts it when it claims it
            self.ready.set()
            self._wake()  # while this thread finishes on_frame and settles

        try:
            try:
                if _takes_ready(type(self.master)):
                    result = self.master.on_frame(self.entry.frame, events, arrival_ns, ready=frame_ready)
                else:  # a Reconstructor written before the `ready` seam: its frame leaves when on_frame returns
                    result = self.master.on_frame(self.entry.frame, events, arrival_ns)
                if not self.ready.is_set():  # a reconstructor that does not call `ready`
                    frame_ready(result)
            except BaseException as exc:  # re-raised on the worker thread when adopted
                self.error = exc
                self.ready.set()
                self._wake()
            if self.error is None:
                t1 = time.perf_counter()
                self.master.settle()
                self.settle_ms = (time.perf_counter() - t1) * 1e3
                self._catch_up()
        except BaseException as exc:
            self.error = exc
        finally:
            self.ready.set()
            self.done.set()
            self._wake()


class DeblurThread:
    """The "edi-deblur" helper thread, one per worker for its lifetime, started on first use: it runs the jobs it is
    given one at a time, in order. Starting a thread per APS frame instead held the worker in Thread.start for ~1.1
    ms at the median (until the new thread ran), which delayed the latent frames that follow an APS frame.
    `wake` pokes the worker, `deliver` hands a frame to its sinks (both called on this thread)."""

    def __init__(self, wake: Callable[[], None], deliver: Callable[[Reconstruction], None]) -> None:
        self.wake, self.deliver = wake, deliver
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def run(self, job: Callable[[], None]) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="edi-deblur", daemon=True)
            self._thread.start()
        self._jobs.put(job)

    def close(self) -> None:
        """The thread ends after the jobs given so far (it is a daemon: nobody waits for it)."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread = None

    def _loop(self) -> None:
        while (job := self._jobs.get()) is not None:
            job()  # PendingDeblur._run: catches everything, reports through the PendingDeblur


class StreamingCopy:
    """The worker's reconstructor while a deblur is pending: the master's streaming copy, logging into the
    PendingDeblur each call that moves its state (on_events, on_events_frames, render) until a gap; everything
    else is the copy's own."""

    def __init__(self, copy: Reconstructor, pending: PendingDeblur) -> None:
        self._copy, self._pending = copy, pending

    def __getattr__(self, name: str) -> Any:
        return getattr(self._copy, name)

    @property
    def original(self) -> Reconstructor:
        """The reconstructor deblurring on the helper thread: the one the stats describe (the copy watches no
        flicker and runs no calibration). Its plain values are safe to read from another thread."""
        return self._pending.master

    def on_events(self, events: np.ndarray, arrival_ns: int = 0) -> None:
        if not self._pending.gap:
            self._pending.calls.append((events, arrival_ns, None, None))
        self._copy.on_events(events, arrival_ns)

    def on_events_frames(self, events: np.ndarray, cuts: Sequence[int],
                         arrivals: Sequence[int]) -> list[Reconstruction]:
        if not self._pending.gap:
            self._pending.calls.append((events, 0, list(cuts), list(arrivals)))
        return self._copy.on_events_frames(events, cuts, arrivals)

    def render(self) -> Reconstruction:
        if not self._pending.gap:
            self._pending.calls.append(())
        return self._copy.render()


@functools.cache
def _takes_ready(cls: type) -> bool:
    """Whether cls.on_frame accepts the `ready` callback (a parameter of that name, or **kwargs). Per class, once:
    inspecting the signature costs ~12 µs, on the deblurred frame's path."""
    try:
        params = inspect.signature(cls.on_frame).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == "ready" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)

