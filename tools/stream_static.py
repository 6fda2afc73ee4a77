"""The `static` mode of tools/bench_stream.py: the node's CPU on a still scene seen by a perfect sensor (APS frames,
no events), from StaticSource, a source that stands in for such a camera."""

from __future__ import annotations

import threading
import time

import numpy as np

from edi_live.config import NodeConfig
from edi_live.datatypes import EVENT_DTYPE, Frame, Packet, SourceInfo, SourceStatus
from edi_live.node import Node


class StaticSource:
    """A camera looking at a still scene with a perfect sensor: APS frames at `fps`, no events."""

    def __init__(self, width: int = 240, height: int = 180, fps: float = 20.0, exposure_us: int = 10_000) -> None:
        self.info = SourceInfo(width, height, name="static", kind="replay")
        self.fps, self.exposure_us = fps, exposure_us
        self._stop = threading.Event()
        self._image = np.random.default_rng(0).integers(20, 235, (height, width)).astype(np.uint8)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._stop.set()

    def stop(self):
        self._stop.set()

    def status(self):
        return SourceStatus()

    def __iter__(self):
        t0_s = time.monotonic()
        k = 0
        while not self._stop.is_set():
            due = t0_s + k / self.fps
            if self._stop.wait(max(0.0, min(0.1, due - time.monotonic()))):
                return
            if time.monotonic() < due:
                yield None
                continue
            t_us = int(k * 1e6 / self.fps)
            frame = Frame(self._image, exposure_start_us=t_us, exposure_end_us=t_us + self.exposure_us)
            yield Packet(events=np.zeros(0, EVENT_DTYPE), frames=[frame], watermark_us=t_us + self.exposure_us,
                         arrival_ns=time.monotonic_ns())
            k += 1


def bench_static(seconds: float) -> None:
    print(f"\n## static scene: 240x180, APS at 20 fps, no events, {seconds:.0f} s after a 2 s warm-up (node with "
          f"publisher)")
    cfg = NodeConfig.from_options({"device": "auto", "publish": ["tcp://127.0.0.1:*"]})
    node = Node(cfg, StaticSource())
    result: dict = {}
    thread = threading.Thread(target=lambda: result.setdefault("stats", node.run()), daemon=True)
    thread.start()
    node.started.wait(30)
    time.sleep(2.0)  # JIT loading and the first deblur are start-up costs, not the steady state
    s0 = node.stats()
    cpu0, wall0 = time.process_time(), time.monotonic()
    time.sleep(seconds)
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    s1 = node.stats()
    node.stop()
    thread.join(30)
    print(f"process CPU {cpu:.3f} s over {wall:.1f} s wall = {100 * cpu / wall:.2f} % of one core; in that time: "
          f"APS frames in {s1['aps_frames_in'] - s0['aps_frames_in']}, deblurred "
          f"{s1['aps_frames_in'] - s0['aps_frames_in'] - (s1['skipped_static_deblur'] - s0['skipped_static_deblur'])}"
          f", frames out {s1['frames_out'] - s0['frames_out']} (heartbeats {s1['heartbeats'] - s0['heartbeats']}), "
          f"worker wake-ups {node.worker.wakeups}")
