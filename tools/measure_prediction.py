"""Measures issue 10's quality figure on recordings: how well the node's own output predicted each APS frame.

    python -m tools.measure_prediction FILE.aedat4 [FILE ...] [node options] [--per-frame]
    python -m tools.measure_prediction --cost      # the score's own cost per frame at 240x180 and 346x260

Runs the node's real pipeline in-process on each recording: the replay driver, the event ring and the EDI worker
with the default reconstructor, configured from the same flags as `edi-live` (e.g. --c 0.2, --every 500,
--mode nearest); --speed defaults to 0 (as fast as possible, lossless). A `PredictionScore` (edi_live/quality.py)
sees what the worker sees, on the worker's thread: every event chunk it reads and every APS frame it takes from
the ring (a ring subclass reports both), and every frame it sends (a sink). That is the order the worker will
call it in once the figure is wired in. Prints, per recording, the mean over all scored APS frames of the
prediction PSNR and the no-motion baseline PSNR(B_k, B_k+1), on informative pixels and on active ones.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from edi_live.cli import build_config, options_from_args
from edi_live.errors import EdiLiveError, NodeError
from edi_live.frame_gate import in_event_clock
from edi_live.node import default_reconstructor
from edi_live.quality import PredictionResult, PredictionScore
from edi_live.ring import EventChunk, EventRing, FrameEntry, as_events
from edi_live.worker import EdiWorker

_WORKER_JOIN_S = 600.0


class _ScoredRing(EventRing):
    """The node's ring, telling the score what the worker reads (on the worker thread, in the worker's order)."""

    def __init__(self, score: "_Collector", *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._score = score

    def read_events(self, max_n: int, until_index: int | None = None,
                    through_t_us: int | None = None) -> EventChunk:
        chunk = super().read_events(max_n, until_index, through_t_us)
        self._score.score.on_events(chunk.events)
        return chunk

    def pop_frame(self) -> FrameEntry | None:
        entry = super().pop_frame()
        if entry is not None:
            # as the worker does: the exposure window in the event clock of the offset in use when it is taken
            frame = in_event_clock(entry.frame, self._score.rec.clock_offset_us if self._score.rec else 0)
            self._score.results += self._score.score.on_aps_frame(frame)
        return entry


class _Collector:
    def __init__(self, mode: str) -> None:
        self.score = PredictionScore(mode)
        self.results: list[PredictionResult] = []
        self.rec: Any = None  # the worker's reconstructor (its clock offset places the windows)

    def sink(self, rec: Any) -> None:
        self.results += self.score.on_emitted(rec)


def run_recording(path: str, node_args: Sequence[str]) -> tuple[list[PredictionResult], dict[str, Any]]:
    """Replays `path` through ring + worker with the node options `node_args`; (every APS frame's result, the
    worker's final stats)."""
    import drivers

    flags, config_path = options_from_args(["--replay", path, *node_args])
    flags.setdefault("speed", 0.0)
    cfg = build_config(flags, config_path)
    source = drivers.open_source("replay", path=str(cfg.source.replay), speed=cfg.source.speed)
    info = source.info
    collector = _Collector(cfg.edi.mode)
    ring = _ScoredRing(collector, cfg.ring.capacity_events, cfg.ring.capacity_frames, "wait")
    collector.rec = default_reconstructor(info.width, info.height, cfg.edi)
    worker = EdiWorker(ring, collector.rec, cfg.effective_edi, [collector.sink])
    worker.start()
    try:
        with source:
            for packet in source:
                if packet is None:
                    continue
                packet.events = as_events(packet.events)
                if not ring.push(packet) or worker.done.is_set():
                    break
    finally:
        ring.close()
        if not worker.join(_WORKER_JOIN_S):
            worker.abort()
            raise NodeError(f"the EDI worker did not finish {path} within {_WORKER_JOIN_S:.0f} s")
    if worker.error is not None:
        raise worker.error
    collector.results += collector.score.finish()
    return collector.results, worker.stats()


def _mean(values: list[float | None]) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None


def summarise(results: list[PredictionResult], aps_frames: int) -> dict[str, Any]:
    """Means over all scored APS frames (dB), the gain, and how often the prediction beat no-motion."""
    scored = [r for r in results if r.scored]
    active = [r for r in scored if r.psnr_pred_active_db is not None]
    return {
        "aps_frames": aps_frames,
        "scored": len(scored),
        "pred_db": _mean([r.psnr_pred_db for r in scored]),
        "still_db": _mean([r.psnr_still_db for r in scored]),
        "pred_active_db": _mean([r.psnr_pred_active_db for r in active]),
        "still_active_db": _mean([r.psnr_still_active_db for r in active]),
        "beats": sum(r.psnr_pred_db > r.psnr_still_db for r in scored),
        "frames_per_window": _mean([r.n_frames_used for r in scored]),
        "active_frac": _mean([r.active_px / r.valid_px for r in scored if r.valid_px]),
    }


def measure_cost(width: int, height: int, *, aps_frames: int = 200, frames_per_interval: int = 40,
                 events_per_frame: int = 1000, seed: int = 0) -> dict[str, float]:
    """Wall time of PredictionScore fed like the causal worker: APS frames every 40 ms with a 20 ms exposure,
    `frames_per_interval` latent frames evenly spaced (half of them inside the next exposure), each after
    `events_per_frame` events. Returns µs per emitted frame (all calls included), per APS frame, ns per event."""
    import time

    from edi_live.datatypes import EVENT_DTYPE, Frame, Reconstruction

    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, (height, width), dtype=np.uint8) for _ in range(8)]
    events = np.zeros(events_per_frame, EVENT_DTYPE)
    events["x"] = rng.integers(0, width, events_per_frame)
    events["y"] = rng.integers(0, height, events_per_frame)
    score = PredictionScore("causal")
    t_emit = t_aps = t_events = 0.0
    period, exposure = 40_000, 20_000
    step = period // frames_per_interval
    ref = None
    n_emitted = 0
    for k in range(aps_frames):
        start = k * period + (period - exposure)
        if ref is not None:
            for j in range(frames_per_interval):
                t0 = time.perf_counter()
                score.on_events(events)
                t1 = time.perf_counter()
                rec = Reconstruction(images[j % 8], start - period + exposure + (j + 1) * step, "latent", ref,
                                     0, 0, 0.2, 0.2, events_per_frame)
                score.on_emitted(rec)
                t2 = time.perf_counter()
                t_events += t1 - t0
                t_emit += t2 - t1
                n_emitted += 1
        frame = Frame(images[k % 8], start, start + exposure, seq=k)
        t0 = time.perf_counter()
        score.on_aps_frame(frame)
        t1 = time.perf_counter()
        ref = frame.mid_exposure_us
        score.on_emitted(Reconstruction(images[k % 8], ref, "deblurred", ref, start, start + exposure, 0.2, 0.2, 0))
        t2 = time.perf_counter()
        t_aps += t1 - t0
        t_emit += t2 - t1
        n_emitted += 1
    return {"us_per_emitted_frame": 1e6 * t_emit / n_emitted, "us_per_aps_frame": 1e6 * t_aps / aps_frames,
            "ns_per_event": 1e9 * t_events / max(1, n_emitted - aps_frames) / events_per_frame,
            "us_per_emitted_frame_all_in": 1e6 * (t_emit + t_aps + t_events) / n_emitted,
            "scored": float(score.scored_total)}


def _fmt(v: float | None, spec: str = "6.2f") -> str:
    return format(v, spec) if v is not None else " " * (int(spec.split(".")[0]) - 1) + "-"


def _split_node_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """(this tool's arguments, the node options), the value of a node option kept with it: parse_known_args alone
    took the value of '--c 0.3 FILE' for a file name, and ran FILE with a bare '--c'."""
    from edi_live.cli_parser import build_parser

    takes_value = {name: action.nargs != 0 for action in build_parser()._actions for name in action.option_strings}
    own, node = [], []
    i = 0
    while i < len(argv):
        arg = argv[i]
        name = arg.split("=", 1)[0]
        if name in takes_value and name not in ("-h", "--help"):
            node.append(arg)
            if takes_value[name] and "=" not in arg and i + 1 < len(argv):
                node.append(argv[i + 1])
                i += 1
        else:
            own.append(arg)
        i += 1
    return own, node


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.measure_prediction", description=__doc__.split("\n")[0],
                                     allow_abbrev=False,  # --c is a node option, not short for --cost
                                     epilog="Any other option is a node option (see edi-live --help).")
    parser.add_argument("files", nargs="*", metavar="FILE.aedat4")
    parser.add_argument("--cost", action="store_true",
                        help="measure the score's own cost at 240x180 and 346x260 (no recording needed)")
    parser.add_argument("--per-frame", action="store_true", help="also print every APS frame's result")
    own, node_args = _split_node_options(sys.argv[1:] if argv is None else list(argv))
    args = parser.parse_args(own)
    if args.cost:
        for w, h in ((240, 180), (346, 260)):
            c = measure_cost(w, h)
            print(f"{w}x{h}: {c['us_per_emitted_frame']:.1f} us per emitted frame (scoring included), "
                  f"{c['us_per_aps_frame']:.1f} us per APS frame, {c['ns_per_event']:.1f} ns per event; "
                  f"all in: {c['us_per_emitted_frame_all_in']:.1f} us per emitted frame ({c['scored']:.0f} scored)")
        if not args.files:
            return 0
    if not args.files:
        parser.error("give at least one FILE.aedat4 (or --cost)")
    print(f"node options: {' '.join(node_args) or '(defaults)'}")
    print(f"{'recording':32s} {'c_on':>6s} {'c_off':>6s} {'scored':>7s} {'pred':>6s} {'still':>6s} {'gain':>6s} "
          f"{'pred_a':>6s} {'still_a':>6s} {'gain_a':>6s} {'beats':>6s} {'fr/exp':>6s} {'act%':>5s}")
    for path in args.files:
        try:
            results, wstats = run_recording(path, node_args)
        except EdiLiveError as exc:
            print(f"measure_prediction: error: {exc}", file=sys.stderr)
            return 1
        s = summarise(results, int(wstats["aps_frames_in"]))
        gain = None if s["pred_db"] is None else s["pred_db"] - s["still_db"]
        gain_a = None if s["pred_active_db"] is None else s["pred_active_db"] - s["still_active_db"]
        print(f"{Path(path).name:32s} {wstats['c_on']:6.3f} {wstats['c_off']:6.3f} "
              f"{s['scored']:3d}/{s['aps_frames']:<3d} {_fmt(s['pred_db'])} {_fmt(s['still_db'])} {_fmt(gain, '+6.2f')} "
              f"{_fmt(s['pred_active_db'])} {_fmt(s['still_active_db'])} {_fmt(gain_a, '+6.2f')} "
              f"{s['beats']:3d}/{s['scored']:<2d} {_fmt(s['frames_per_window'], '6.1f')} "
              f"{_fmt(None if s['active_frac'] is None else 100 * s['active_frac'], '5.1f')}")
        if not s["scored"]:  # a row of dashes alone reads like a broken tool
            why = ("it holds no APS frames: the figure compares the node's output with each APS frame"
                   if not s["aps_frames"] else
                   f"none of its {s['aps_frames']} APS frame(s) could be predicted (each needs an earlier one "
                   f"and the events between them)")
            print(f"measure_prediction: {path}: nothing scored, {why}", file=sys.stderr)
        if args.per_frame:
            for r in results:
                print(f"    seq {r.seq:4d} t {r.t_us} exp {r.exposure_end_us - r.exposure_start_us:6d} us "
                      f"frames {r.n_frames_used:3d} cov {r.coverage:4.2f} pred {_fmt(r.psnr_pred_db)} "
                      f"still {_fmt(r.psnr_still_db)} pred_a {_fmt(r.psnr_pred_active_db)} "
                      f"still_a {_fmt(r.psnr_still_active_db)} active {r.active_px}/{r.valid_px}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
