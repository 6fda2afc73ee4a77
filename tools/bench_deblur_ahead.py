"""Deblur time per APS frame with and without the running double integral (edi_live/exposure_ahead.py).

The reconstructor is fed as the worker feeds it: the events in chunks as they come, each APS frame at its exposure
end with every event from its exposure start on. Both variants run alternately on the same recording; the table
gives each run's median on_frame wall time (ms, the first 4 frames left out: the prediction needs three regular
windows) and the ratio of the two in each pair (median, min, max), so a shared machine's load cancels out.
It also gives the thread CPU time per frame of on_frame, of on_frame until it hands the frame to its `ready`
callback (what the deblurred frame waits for on the deblur thread: the rest of on_frame readies the state for the
events after the frame) and of settle() (the calibration work run after the frame was sent, as the worker does):
on_frame + settle is what a frame waited for before settle() existed. Medians per run over the frames after the
first 4.

    python -m tools.bench_deblur_ahead RECORDING.aedat4 [--repeat 5] [--c 0.2]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import edi_live.edi as edi
from edi_live.reconstructor import EdiReconstructor
from tools.figure import load_recording


def deblur_ms(events: np.ndarray, frames: list, rec: EdiReconstructor, chunk: int = 1000,
              cpu: list | None = None) -> list[float]:
    """on_frame wall ms per frame; `cpu`, if a list, gets (on_frame, settle, on_frame up to its `ready` callback,
    i.e. until the deblur thread may send the frame) thread CPU ms per frame."""
    t = events["t"]
    out, pos = [], 0
    for f in frames:
        end = int(np.searchsorted(t, f.exposure_end_us, side="right"))
        while pos < end:
            nxt = min(pos + chunk, end)
            rec.on_events(events[pos:nxt])
            pos = nxt
        ready: list[float] = []
        c0 = time.thread_time()
        rec.on_frame(f, edi.window(events[:pos], f.exposure_start_us, None),
                     ready=lambda _frame: ready.append(time.thread_time()))
        c1 = time.thread_time()
        rec.settle()  # the worker's order: after the frame was sent
        if cpu is not None:
            cpu.append(((c1 - c0) * 1e3, (time.thread_time() - c1) * 1e3, (ready[0] - c0) * 1e3))
        out.append(rec.last_deblur_ms)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_deblur_ahead", description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--c", type=float, default=None, help="a fixed c (default: estimated)")
    args = ap.parse_args(argv)
    events, frames = load_recording(args.recording)
    h, w = frames[0].image.shape[:2]
    knobs = {} if args.c is None else {"c": args.c}
    runs: dict[bool, list[float]] = {True: [], False: []}
    used = 0
    split: list[tuple[float, ...]] = []  # per ahead run: medians of on_frame, settle, their sum, to ready (CPU ms)
    for _ in range(args.repeat):
        for ahead in (True, False):
            rec = EdiReconstructor(w, h, deblur_ahead=ahead, clock_offset_us=0, **knobs)
            cpu: list[tuple[float, float]] = []
            runs[ahead].append(float(np.median(deblur_ms(events, frames, rec, cpu=cpu)[4:])))
            if ahead:
                used = rec.stats()["deblurs_ahead"]
                a = np.array(cpu[4:]).reshape(-1, 3)
                split.append((float(np.median(a[:, 0])), float(np.median(a[:, 1])),
                              float(np.median(a[:, 0] + a[:, 1])), float(np.median(a[:, 2]))))
    ratio = np.array(runs[False]) / np.array(runs[True])
    print(f"{args.recording.name}: {len(frames)} APS frames, {used} deblurred from the running integral; "
          f"c {'fixed ' + str(args.c) if args.c is not None else 'estimated'}, clock offset given (0)")
    print("on_frame ms, median per run: ahead " + " ".join(f"{v:.2f}" for v in runs[True])
          + " | read at the end " + " ".join(f"{v:.2f}" for v in runs[False]))
    print(f"read-at-the-end / ahead: median {np.median(ratio):.2f} (min {ratio.min():.2f}, max {ratio.max():.2f})")
    sp = np.array(split)
    print("thread CPU ms per frame (ahead runs, median per run): on_frame " + " ".join(f"{v:.2f}" for v in sp[:, 0])
          + " | settle " + " ".join(f"{v:.2f}" for v in sp[:, 1])
          + " | on_frame + settle " + " ".join(f"{v:.2f}" for v in sp[:, 2])
          + " | on_frame until the frame is ready " + " ".join(f"{v:.2f}" for v in sp[:, 3]))
    share = sp[:, 0] / sp[:, 2]
    print(f"on_frame / (on_frame + settle): median {np.median(share):.2f} (min {share.min():.2f}, "
          f"max {share.max():.2f})")


if __name__ == "__main__":
    main()
