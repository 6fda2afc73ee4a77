"""The composition root and supervisor: source -> [pump] -> ring -> [edi-worker] -> publisher / out-writer.

`Node(config, source).run()` opens the source, builds the ring, reconstructor, publisher and writers, starts the
threads, supervises them from the calling (main) thread, stops them in flow order and returns the final stats;
it re-raises the first failure of any thread on the calling thread.

Threads ([name]):
- [pump] iterates the source (so a driver's decoding runs here), pushes each packet into the ring (policy
  "wait" for replay: lossless; "drop_oldest" live: never blocks the driver) and tees it to [record-writer].
- [edi-worker] (worker.py), [publisher] (publisher.py), [out-writer] / [record-writer] (writers.py).

Start order is reverse flow order: the source is opened first only because its resolution sizes everything
downstream, then the publisher (a failed bind is fatal here, before any data flows or any file is created), the
writers, the worker, and the pump last. Stop is in flow order: source, pump (closes the ring), worker (drains what was received), publisher
(sends what it holds, linger 0), writers (finalise their files), then the source is released.

Failures: every thread hands its exception to `fail()`; the first one is kept. A source fault (truncated file,
unplugged camera) only ends the input: data already received still flows to the sinks and files are finalised,
then run() raises. Any other fault aborts the worker at once. Every join has a timeout; a thread that does not
stop is named in a NodeError.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable, ContextManager, TextIO


from edi_live import calibration, fused_mode
from edi_live.config import EdiConfig, NodeConfig
from edi_live.errors import ConfigError, EdiLiveError, NodeError, OutputError, SourceError
from edi_live.frame_demand import nobody_wants
from edi_live.reconstruction import Reconstructor
from edi_live.ring import EventRing, as_events
from edi_live.source import Source, stop_from_another_thread
from edi_live.stats import Rates, StatusLine, collect, with_rates
from edi_live.warm_up import warm_up
from edi_live.worker import EdiWorker
from edi_live.writers import OutWriter, RecordWriter

log = logging.getLogger(__name__)

ReconstructorFactory = Callable[[int, int, EdiConfig], Reconstructor]
PublisherFactory = Callable[..., Any]

_POLL_S = 0.1
_PUMP_JOIN_S = 5.0
_DRAIN_ON_STOP_S = 2.0  # after Ctrl-C/--duration the worker may finish what it holds for this long
_JOIN_S = 5.0


def default_reconstructor(width: int, height: int, edi: EdiConfig) -> Reconstructor:
    """The EDI core's reconstructor with the thresholds and re-estimation policy from the config."""
    from edi_live.reconstructor import EdiReconstructor

    kwargs: dict[str, Any] = {}
    if edi.c is not None:
        kwargs["c"] = edi.c
    if edi.c_on is not None:
        kwargs["c_on"], kwargs["c_off"] = edi.c_on, edi.c_off
    if edi.reestimate_every:
        kwargs["reestimate_every"] = edi.reestimate_every
    kwargs["black_level"] = None if edi.black_level is None else float(edi.black_level)  # None: estimated
    kwargs["clock_offset_us"] = None if edi.clock_offset_us is None else int(edi.clock_offset_us)  # None: estimated
    kwargs["aps_gamma"] = float(edi.aps_gamma or 1.0)
    if edi.start is not None:  # a saved calibration: where the estimates start
        kwargs["c_start"] = (edi.start.c_on, edi.start.c_off)
        kwargs["black_level_start"], kwargs["clock_offset_start_us"] = edi.start.black_level, edi.start.clock_offset_us
    kwargs["color_filter"], kwargs["gray"] = edi.color_filter, bool(edi.gray)
    kwargs["deblur_ahead"] = bool(edi.deblur_ahead)
    kwargs["mask_flicker_pixels"] = edi.mode != "fused" if edi.flicker_mask is None else bool(edi.flicker_mask)
    kwargs["fused_residual"], kwargs["divisor_median"] = bool(edi.fused_residual), bool(edi.divisor_median)
    kwargs["latent_denoise"] = bool(edi.latent_denoise) and edi.mode == "causal"  # (cli warns otherwise)
    kwargs["noise_stats"], kwargs["noise_rate_hz"], kwargs["noise_start"] = (
        bool(edi.noise_stats), edi.noise_rate_hz, None if edi.start is None else edi.start.noise)
    if edi.mode == "fused":
        kwargs["joint_pairs"] = fused_mode.JOINT_PAIRS
    return EdiReconstructor(width, height, **kwargs)


def default_publisher(**kwargs: Any) -> Any:
    from edi_live.publisher import Publisher

    return Publisher(**kwargs)


class Node:
    """Runs one source through the pipeline until the input ends, stop() is called, or --duration passes."""

    def __init__(self, config: NodeConfig, source: Source, *,
                 reconstructor_factory: ReconstructorFactory = default_reconstructor,
                 publisher_factory: PublisherFactory = default_publisher,
                 status_stream: TextIO | None = None) -> None:
        self.config = config
        self.source = source
        self._make_reconstructor = reconstructor_factory
        self._make_publisher = publisher_factory
        self._status_stream = status_stream
        self.ring: EventRing | None = None
        self.worker: EdiWorker | None = None
        self.publisher: Any = None
        self._entering = False  # the source is being opened (__enter__)
        self._calibration_to: Path | None = None  # where the calibration in use is saved at the end
        self._calibration_start = None  # the calibration the run started from (its measured black level stays so)
        self.out_writer: OutWriter | None = None
        self.record_writer: RecordWriter | None = None
        self.dv_frames: Any = None  # edi_live.dv_output.DvOutput of the sharp frames (--dv-output)
        self.dv_events: Any = None  # ... of the input events (--dv-output-events)
        self._pump: threading.Thread | None = None
        self._lock = threading.Lock()
        self._failure: tuple[BaseException, str] | None = None
        self._stop = threading.Event()
        self._aborting = threading.Event()
        self._started = threading.Event()
        self._rates = Rates()
        self.t_start = 0.0
        self.warm_up_s = 0.0  # the one-off kernel compile (cold cache) or load, before the source is opened
        self.elapsed_s = 0.0  # the run itself, after the warm-up: the summary's rates divide by this
        self.final_stats: dict[str, Any] = {}

    # ---------------------------------------------------------------- any thread

    def stop(self) -> None:
        """Ask the node to stop (Ctrl-C, SIGTERM, --duration). Safe from signal handlers and other threads."""
        self._stop.set()
        if self._entering:  # a source waiting while it opens
            stop_from_another_thread(self.source.stop)

    def fail(self, exc: BaseException, thread: str = "main", input_fault: bool = False) -> None:
        """Record a thread's failure (the first one wins). A fault of the input lets received data drain;
        any other fault aborts at once."""
        with self._lock:
            if self._failure is None:
                self._failure = (exc, thread)
                log.debug("%s failed", thread, exc_info=exc)
            elif isinstance(exc, EdiLiveError):  # e.g. --record lost too: only the first is the run's error line
                log.warning("%s", exc)
            else:
                log.debug("%s also failed: %s", thread, exc)
        if not input_fault:
            self._aborting.set()
            if self.worker is not None:
                self.worker.abort()
            if self.ring is not None:
                self.ring.close()
            self._stop.set()

    def stats(self) -> dict[str, Any]:
        """Every counter of every stage (see stats.collect)."""
        out = collect(self.source, self.ring, self.worker, self.publisher,
                      (self.out_writer, self.record_writer, self.dv_frames, self.dv_events))
        out["warm_up_s"] = round(self.warm_up_s, 3)
        return out

    def stats_map(self) -> dict[str, Any]:
        """The map for the publisher's once-a-second stats message (it adds its own latency figures)."""
        s = with_rates(self.stats(), self._rates)
        keep = ("warm_up_s", "events_per_s", "frames_per_s", "c", "c_on", "c_off", "reestimations", "hot_pixels", "drops",
                "ring_occupancy", "ring_dropped_events", "ring_dropped_frames", "events_in", "events_processed",
                "aps_frames_in", "frames_deblurred", "frames_latent", "heartbeats", "skipped_max_fps",
                "source_dropped_events", "source_dropped_bytes", "source_gaps", "nearest_added_latency_ms_p50",
                "fused_added_latency_ms_p50", "out_wait_s",
                "unreliable_pixels", "flicker_pixels", "black_level_dn", "clock_offset_us", "aps_gamma", "clock_offset_estimated",
                "clock_offset_physical_us",
                "black_level_estimated", "black_level_from_calibration", "clock_offset_from_calibration", "noise_hz_p50", "noise_hz_p99", "noise_on_hz_p50", "noise_off_hz_p50",
                "noisy_pixels", "pred_psnr_db", "still_psnr_db",
                "pred_gain_db",
                "pred_psnr_active_db", "still_psnr_active_db", "pred_beats_still_frac", "pred_frames_scored",
                "dv_frames_sent", "dv_frames_dropped", "dv_frames_late", "dv_frames_clients", "dv_events_sent",
                "dv_events_dropped", "dv_events_clients")
        return {k: s[k] for k in keep if k in s and s[k] is not None}

    @property
    def bound_endpoints(self) -> list[str]:
        return [] if self.publisher is None else list(self.publisher.bound_endpoints)

    @property
    def started(self) -> threading.Event:
        """Set once every thread runs (the publisher is bound)."""
        return self._started

    # ---------------------------------------------------------------- main thread

    def run(self, warming_up: Callable[[], ContextManager[Any]] = contextlib.nullcontext) -> dict[str, Any]:
        """Run to the end; returns the final stats. Raises the first failure (EdiLiveError subclasses as they
        are, anything else wrapped in NodeError naming the thread). `warming_up`: the context the kernel warm-up
        runs in, before anything is opened (the command line's StopSignals.raising: a stop signal ends it at once)."""
        self.t_start = time.monotonic()
        entered = False
        with warming_up():
            warm_up(self._make_reconstructor, self.config.edi)
        try:
            # the run's clock starts after the warm-up: a cold numba cache compiles for seconds once, which must
            # not be folded into the rates of the summary (it is reported on its own line)
            self.warm_up_s = time.monotonic() - self.t_start
            self.t_start += self.warm_up_s
            if self._stop.is_set():  # stopped during start-up (SIGTERM, Ctrl-C): open nothing, create no file
                return self.final_stats
            self._entering = True  # stop() reaches a source that waits while opening (a camera, --reconnect)
            self.source.__enter__()
            entered, self._entering = True, False
            if self._stop.is_set():  # stopped while the source opened: nothing was received
                return self.final_stats
            self._build_and_start()
            self._started.set()
            self._supervise()
        except BaseException as exc:
            if not isinstance(exc, KeyboardInterrupt):
                self.fail(exc, "main")
            else:
                self._stop.set()
        finally:
            try:
                self._shutdown(entered)
            except BaseException as exc:
                self.fail(exc, "main")
            self.elapsed_s = time.monotonic() - self.t_start
            self.final_stats = self.stats()
            self._save_calibration()
        if self._failure is not None:
            exc, thread = self._failure
            if isinstance(exc, EdiLiveError):
                raise exc
            raise NodeError(f"the {thread} thread failed: {type(exc).__name__}: {exc}") from exc
        return self.final_stats

    def _build_and_start(self) -> None:
        cfg = self.config
        info = self.source.info
        self.ring = EventRing(cfg.ring.capacity_events, cfg.ring.capacity_frames, cfg.ring_policy,
                              stop=self._stop.is_set)
        edi_cfg, self._calibration_to = calibration.prepare(cfg.edi, info, cfg.calibration, cfg.save_calibration)
        if cfg.save_calibration is not None:
            calibration.check_can_save(cfg.save_calibration)  # before the run, not after it has measured everything
        self._calibration_start = edi_cfg.start
        # colour: EDI on the Bayer mosaic, with the user's pattern over the source's
        if edi_cfg.color_filter and info.color_filter and edi_cfg.color_filter != info.color_filter:
            log.warning("--bayer-pattern %s replaces the %s pattern %s names: its colours will be wrong unless the "
                        "source is mistaken", edi_cfg.color_filter, info.color_filter, info.label)
        edi_cfg = dataclasses.replace(edi_cfg, color_filter=edi_cfg.color_filter or info.color_filter)
        if edi_cfg.color_filter is not None:
            from edi_live.colour import one_opencv_thread  # OpenCV: loaded for colour sources only

            one_opencv_thread()
            if edi_cfg.latent_denoise and edi_cfg.mode == "causal":  # (the reconstructor leaves it out in silence)
                log.warning("ignored with a colour camera: --latent-denoise (it compares a pixel with its 8 "
                            "neighbours, which see other colours on a Bayer mosaic)")
        reconstructor = self._make_reconstructor(info.width, info.height, edi_cfg)
        sinks = []
        if cfg.publisher.enabled:
            self.publisher = self._make_publisher(
                endpoints=list(cfg.publisher.endpoints), source=info.label,
                curve_secret_key=cfg.publisher.curve_secret_key, stats_provider=self.stats_map,
                stats_interval_s=cfg.publisher.stats_interval_s, on_error=lambda e: self.fail(e, "publisher"))
            self.publisher.start()
            sinks.append(self.publisher.submit)
            log.info("publishing on %s", ", ".join(self.bound_endpoints))
        self._start_dv_outputs(sinks)
        if cfg.output.out is not None:
            self.out_writer = OutWriter(cfg.output.out, info.width, info.height, camera_name=info.label,
                                        queue_items=cfg.output.queue_items,
                                        on_error=lambda e: self.fail(e, "out-writer"))
            self.out_writer.start()
        if cfg.output.record is not None:
            self.record_writer = RecordWriter(cfg.output.record, info.width, info.height, camera_name=info.label,
                                              queue_items=cfg.output.queue_items, color_filter=edi_cfg.color_filter,
                                              on_error=lambda e: self.fail(e, "record-writer"))
            self.record_writer.start()
        if self.out_writer is not None:
            sinks.append(self.out_writer.submit)
        # latent frames nobody would receive are not rendered: with the publisher as the only sink, while no
        # subscriber listens; with no sink at all (--no-publish without --out or --dv-output), ever
        only_publisher = self.publisher is not None and sinks == [self.publisher.submit]
        # nor scored: the prediction figure is of frames someone received, and with no sink nobody receives any
        worker_cfg = cfg.effective_edi if sinks else dataclasses.replace(cfg.effective_edi, quality_every=0)
        self.worker = EdiWorker(self.ring, reconstructor, worker_cfg, sinks,
                                on_error=lambda e: self.fail(e, "edi-worker"),
                                frames_wanted=(nobody_wants if not sinks else
                                               self.publisher.wants_frames if only_publisher else None))
        self.worker.start()
        self._pump = threading.Thread(target=self._pump_loop, name="pump", daemon=True)
        self._pump.start()

    def _save_calibration(self) -> None:
        """--save-calibration (a failure is the run's error), or a live camera's own file (a failure is a warning)."""
        target = self._calibration_to
        # no worker: the start-up failed after the target was chosen (--out not creatable, a port in use), so
        # nothing was measured and that failure is the run's one line, not also "nothing to save"
        if target is None or self.worker is None:
            return
        noise = self.worker.noise_rates()
        try:
            cal = calibration.measured(self.source.info, self.final_stats, noise, self._calibration_start,
                                       self.config.edi.black_level is not None, target)
            if cal is not None:
                calibration.save(cal, target)
                log.info("calibration saved to %s", target)
        except (ConfigError, OutputError) as exc:
            if self.config.save_calibration is not None:
                self.fail(exc, "calibration", input_fault=True)
            else:
                log.warning("%s", exc)

    def _start_dv_outputs(self, sinks: list) -> None:
        """--dv-output / --dv-output-events: DV network servers beside the publisher (bind errors are fatal here)."""
        from edi_live.dv_output import DvOutput

        info, out = self.source.info, self.config.output
        for attr, endpoint, stream in (("dv_frames", out.dv_output, "frames"),
                                       ("dv_events", out.dv_output_events, "events")):
            if endpoint is None:
                continue
            server = DvOutput(endpoint, stream, info.width, info.height, camera_name=info.label,
                              on_error=lambda e, s=stream: self.fail(e, f"dv-output-{s}"))
            server.start()
            setattr(self, attr, server)
            log.info("serving DV %s on %s", stream, server.bound_endpoint)
        if self.dv_frames is not None:
            sinks.append(self.dv_frames.submit)

    def _pump_loop(self) -> None:
        """[pump] thread: source -> ring (and --record, --dv-output-events)."""
        ring, record, dv_events = self.ring, self.record_writer, self.dv_events
        try:
            for packet in self.source:
                if self._stop.is_set():
                    break
                if packet is None:
                    continue
                packet.events = as_events(packet.events)
                if record is not None:
                    record.submit(packet)
                if dv_events is not None:
                    dv_events.submit(packet)
                if not ring.push(packet):
                    break  # the ring was closed: we are stopping
        except BaseException as exc:
            self.fail(exc, "pump", input_fault=isinstance(exc, SourceError))
        finally:
            ring.close()

    def _supervise(self) -> None:
        duration = self.config.duration_s
        status = None
        if self._status_stream is not None:
            status = StatusLine(self._status_stream, self.config.status_interval_s)
        try:
            while not self.worker.done.is_set() and not self._stop.is_set():
                self._stop.wait(_POLL_S)
                if duration is not None and time.monotonic() - self.t_start >= duration:
                    log.info("--duration %g s reached", duration)
                    self._stop.set()
                if status is not None:
                    status.maybe_draw(self.stats)
        finally:
            if status is not None:
                status.finish()

    def _shutdown(self, entered: bool) -> None:
        """Stop in flow order; every join has a timeout. Collects the first error, raises nothing."""
        stuck: list[str] = []

        def guard(what: str, fn: Callable[[], Any]) -> None:
            try:
                fn()
            except BaseException as exc:
                self.fail(exc, what, input_fault=True)

        if entered:
            guard("source", self.source.stop)
        if self._pump is not None:
            self._pump.join(_PUMP_JOIN_S / 2)
            if self._pump.is_alive():  # stuck in a push: closing the ring releases it
                self.ring.close()
                self._pump.join(_PUMP_JOIN_S / 2)
                if self._pump.is_alive():
                    stuck.append("pump")
        if self.worker is not None:
            if self.ring is not None:
                self.ring.close()
            drain_s = _JOIN_S if not (self._stop.is_set() or self._aborting.is_set()) else _DRAIN_ON_STOP_S
            if self._aborting.is_set():
                self.worker.abort()
            if not self.worker.join(drain_s):
                self.worker.abort()
                if not self.worker.join(_JOIN_S):
                    stuck.append("edi-worker")
        if self.publisher is not None:
            guard("publisher", lambda: self.publisher.close(timeout_s=2.0))
        for writer in (self.dv_frames, self.dv_events, self.out_writer, self.record_writer):
            if writer is not None:
                guard(writer.name, lambda w=writer: w.close(timeout_s=10.0))
        if entered:
            guard("source", lambda: self.source.__exit__(None, None, None))
        if stuck:
            self.fail(NodeError(f"thread(s) {', '.join(stuck)} did not stop within their timeout"), "main")

    def __enter__(self) -> "Node":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
