"""The A/B modes of tools/profile_node_cpu.py: `ab` (node CPU of the full node) and `worker` (worker-thread CPU),
each variant run in alternating child processes started in its own checkout, so that each imports that checkout's
edi_live; the child scripts, and the tables of their figures and of the ratios per pair."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np


_CHILD = """
import json, sys, time
from pathlib import Path
from tools.bench_stream import run_with_subscriber
if sys.argv[4] == "1":
    stats, sub, wall_s, pub = run_with_subscriber(Path(sys.argv[1]), {"every": int(sys.argv[2]),
                                                  **json.loads(sys.argv[5])}, speed=0, passes=int(sys.argv[3]))
else:  # publishing, nobody subscribed
    import drivers
    from edi_live.config import NodeConfig
    from edi_live.node import Node
    cfg = NodeConfig.from_options({"replay": sys.argv[1], "speed": 0, "publish": ["tcp://127.0.0.1:*"],
                                   "every": int(sys.argv[2]), "loop": True})
    source = drivers.open_source("replay", path=sys.argv[1], speed=0, loop=True, decode_process=True)
    node = Node(cfg, source)
    import threading
    started = {}
    def stop_after_passes():
        node.started.wait(60)
        started["cpu_s"] = time.process_time()  # after the kernels' warm-up
        while getattr(source, "loops", 0) < int(sys.argv[3]) and not node.final_stats:
            time.sleep(0.01)
        node.stop()
    threading.Thread(target=stop_after_passes, daemon=True).start()
    stats = node.run()
    stats["node_cpu_s"], sub, wall_s = time.process_time() - started["cpu_s"], {}, 0.0
print(json.dumps({"cpu_s": stats["node_cpu_s"], "events": stats["events_processed"], "frames": sub.get("frames"),
                  "emitted": stats["frames_out"], "gaps": sub.get("seq_gaps"), "wall_s": wall_s}))
"""


def ab(other: Path, paths: list[Path], every: int, repeat: int, passes: int, subscribers: int = 1,
       options: dict | None = None) -> None:
    """`options`: node options of the new side only (with a subscriber)."""
    here = Path(__file__).resolve().parent.parent
    print(f"\n## A/B node CPU: new = {here} {options or ''}, old = {other}; --every {every}, {passes} passes, "
          f"{repeat} pairs, {subscribers} subscriber(s)")
    for path in paths:
        runs: dict[str, list[dict]] = {"old": [], "new": []}
        for i in range(repeat):
            order = ("old", "new") if i % 2 == 0 else ("new", "old")
            for which in order:
                cwd = other if which == "old" else here
                out = subprocess.run([sys.executable, "-c", _CHILD, str(path), str(every), str(passes),
                                      str(subscribers), json.dumps(options or {} if which == "new" else {})],
                                     cwd=cwd,
                                     capture_output=True, text=True)
                if out.returncode != 0:
                    raise SystemExit(f"{which} run failed:\n{out.stderr[-2000:]}")
                runs[which].append(json.loads(out.stdout.strip().splitlines()[-1]))
        ratios = [o["cpu_s"] / n["cpu_s"] for o, n in zip(runs["old"], runs["new"])]
        print(f"\n{path.name}: events {runs['new'][0]['events']}, frames received new "
              f"{[r['frames'] for r in runs['new']]} / emitted {runs['new'][0]['emitted']}, "
              f"old {[r['frames'] for r in runs['old']]} / {runs['old'][0]['emitted']}")
        for which in ("old", "new"):
            per = [r["events"] / r["cpu_s"] / 1e6 for r in runs[which]]
            print(f"  {which}: node CPU s {[round(r['cpu_s'], 3) for r in runs[which]]}; M events per node-CPU-s "
                  f"median {np.median(per):.2f} ({min(per):.2f}-{max(per):.2f})")
        print(f"  old CPU / new CPU per pair: median {np.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})")


_WORKER_CHILD = """
import json, sys, time
import drivers
from edi_live.config import EdiConfig
from edi_live.node import default_reconstructor
from edi_live.ring import EventRing
from edi_live.worker import EdiWorker
path, every, passes, extra = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), json.loads(sys.argv[4])
def filled():
    src = drivers.open_source("replay", path=path, speed=0, loop=passes > 1)
    ring = EventRing(1 << 26, 1 << 14, "wait")
    with src:
        for packet in src:
            if packet is not None and not ring.push(packet, timeout_s=1.0):
                sys.exit("the recording does not fit the ring (2**26 events, 2**14 frames): fewer --passes")
            if passes > 1 and src.loops >= passes:
                break
    ring.close()
    return ring, src.info
cfg = EdiConfig(every=every, deblur_thread=False, **extra)
per_frame = {"on_frame": [], "settle": []}  # thread CPU per APS frame: its deblur, and the checks deferred after it
def timed(cls, name):
    plain = cls.__dict__.get(name)
    if plain is None:  # an older checkout without deferred checks
        return
    def wrapper(self, *args, **kwargs):
        t0 = time.thread_time()
        try:
            return plain(self, *args, **kwargs)
        finally:
            if name == "on_frame":
                per_frame["on_frame"].append(time.thread_time() - t0)
                per_frame["settle"].append(0.0)
            elif per_frame["settle"]:  # settle() runs often; it works once per APS frame
                per_frame["settle"][-1] += time.thread_time() - t0
    setattr(cls, name, wrapper)
for counted in (False, True):  # the first run loads the kernels
    ring, info = filled()
    rec = default_reconstructor(info.width, info.height, cfg)
    if counted:
        for name in per_frame:
            timed(type(rec), name)
    worker = EdiWorker(ring, rec, cfg, [])
    c0 = time.thread_time()
    worker._run()
    cpu_s = time.thread_time() - c0
whole = [a + b for a, b in zip(per_frame["on_frame"], per_frame["settle"])]
med = {k: 1e3 * sorted(v)[len(v) // 2] if v else 0.0 for k, v in (*per_frame.items(), ("whole", whole))}
print(json.dumps({"cpu_s": cpu_s, "events": worker.events_in, "on_frame_ms": med["on_frame"],
                  "frame_ms": med["whole"]}))
"""


def worker_ab(runs: dict[str, tuple[Path, dict]], path: Path, every: int, repeat: int, passes: int) -> None:
    """Worker-thread CPU (ring filled beforehand, no publisher, APS deblur on the worker) of two variants in
    alternating child processes: (checkout, EdiConfig options) each."""
    names = list(runs)
    print(f"\n## worker-thread CPU: {path.name}, --every {every}, {passes} pass(es), {repeat} alternating pairs")
    cpu: dict[str, list[float]] = {k: [] for k in names}
    deblur: dict[str, list[tuple[float, float]]] = {k: [] for k in names}
    events = 0
    for i in range(repeat):
        for name in (names if i % 2 == 0 else names[::-1]):
            cwd, extra = runs[name]
            out = subprocess.run([sys.executable, "-c", _WORKER_CHILD, str(path), str(every), str(passes),
                                  json.dumps(extra)], cwd=cwd, capture_output=True, text=True, timeout=1800)
            if out.returncode != 0:
                raise SystemExit(f"{name} run failed:\n{out.stderr[-2000:]}")
            got = json.loads(out.stdout.strip().splitlines()[-1])
            cpu[name].append(got["cpu_s"])
            deblur[name].append((got["on_frame_ms"], got["frame_ms"]))
            events = got["events"]
    for name in names:
        per = [events / c / 1e6 for c in cpu[name]]
        print(f"  {name}: CPU s {[round(c, 3) for c in cpu[name]]}; M events per worker-CPU-s median "
              f"{np.median(per):.2f} ({min(per):.2f}-{max(per):.2f})")
        ready = [d[0] for d in deblur[name]]
        whole = [d[1] for d in deblur[name]]
        print(f"    per APS frame (thread CPU, median frame of each run): deblur until the frame is ready "
              f"{np.median(ready):.3f} ms ({min(ready):.3f}-{max(ready):.3f}), with the checks deferred after it "
              f"{np.median(whole):.3f} ms ({min(whole):.3f}-{max(whole):.3f})")
    ratios = [b / a for a, b in zip(cpu[names[0]], cpu[names[1]])]
    print(f"  {names[1]} / {names[0]} CPU per pair: median {np.median(ratios):.3f} "
          f"({min(ratios):.3f}-{max(ratios):.3f})")
