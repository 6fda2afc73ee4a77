"""The `memory` mode of tools/bench_stream.py: the PSS of the node process and its children (the replay's decoding
child) sampled over a looped replay, with its trend."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from edi_live.config import NodeConfig
from edi_live.node import Node
from tools.stream_harness import replay_source


def _rss_mib() -> float:
    """Memory of this process and all its descendants (the replay decodes in a child process), in MiB: the
    sum of their PSS (shared pages split between the processes that map them, so nothing counts twice), or of
    their RSS where the kernel gives no PSS."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    parent[int(entry)] = int(fh.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    tree, grew = {os.getpid()}, True
    while grew:
        more = {pid for pid, ppid in parent.items() if ppid in tree} - tree
        tree |= more
        grew = bool(more)
    return sum(_pss_kib(pid) for pid in tree) / 1024


def _pss_kib(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return float(line.split()[1])
    except OSError:
        pass
    try:
        with open(f"/proc/{pid}/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024
    except OSError:
        return 0.0


def bench_memory(path: Path, every: int, seconds: float, speed: float) -> None:
    print(f"\n## memory: looped replay --speed {speed} for {seconds:.0f} s, --every {every}, publishing, memory (PSS) "
          f"of the node process and its children (the replay's decoding child)")
    cfg = NodeConfig.from_options({"replay": str(path), "speed": speed, "loop": True, "every": every,
                                   "publish": ["tcp://127.0.0.1:*"], "duration": seconds})
    node = Node(cfg, replay_source(path, speed, loop=True))
    samples: list[tuple[float, float]] = []
    done = threading.Event()

    def sample():
        t_start = time.monotonic()
        while not done.wait(max(1.0, seconds / 30)):
            samples.append((time.monotonic() - t_start, _rss_mib()))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stats = node.run()
    done.set()
    sampler.join(5)
    if len(samples) < 3:
        print("run too short for a trend")
        return
    t = np.array([s[0] for s in samples])
    rss = np.array([s[1] for s in samples])
    half = len(rss) // 2
    slope = np.polyfit(t[half:], rss[half:], 1)[0] * 60
    print("| t s | PSS MiB |\n|---|---|")
    for ts, r in samples[:: max(1, len(samples) // 10)]:
        print(f"| {ts:.0f} | {r:.1f} |")
    print(f"PSS first {rss[0]:.1f} MiB, last {rss[-1]:.1f} MiB, max {rss.max():.1f} MiB; second-half slope "
          f"{slope:+.2f} MiB/min; {stats['events_processed']} events, {stats['frames_out']} frames")
