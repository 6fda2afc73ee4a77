"""End-to-end streaming benchmarks of the edi-live node (numbers, not pass/fail).

    python -m tools.bench_stream throughput   # replay --speed 0 -> worker -> publish -> 1 subscriber, --every 1000
    python -m tools.bench_stream stages       # CPU per stage, each alone on one thread (per frame / per event)
    python -m tools.bench_stream latency      # paced replay at ~1 M events/s: latency p50/p99, arrival -> sent
    python -m tools.bench_stream memory       # PSS over a looped replay (--seconds 60; 600 for the 10-minute run)
    python -m tools.bench_stream static       # CPU of the node on a static scene (APS frames, no events)
    python -m tools.bench_stream noise        # static scene with sensor noise: CPU, frames out, motion-onset delay
    python -m tools.bench_stream noise --against ../main   # the same, A/B against another checkout
    python -m tools.bench_stream scaling      # worker cost per latent frame vs changed pixels and resolution
    python -m tools.bench_stream all

Input: `--input FILE.aedat4`, or by default a 240x180 recording simulated once by tools/simulate.py (preset
"fast") and cached in the temp directory. The subscriber runs in its own process, as a viewer would.
Figures are medians of `--repeat` runs where it makes sense; each mode prints what limits it.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from edi_live.config import NodeConfig
from edi_live.datatypes import EVENT_DTYPE, Frame, Packet, SourceInfo, SourceStatus
from edi_live.node import Node, default_reconstructor


# ------------------------------------------------------------------------------------------------ inputs

def default_recording(width: int = 240, height: int = 180) -> Path:
    """A simulated fast-motion recording, generated once (a few seconds) and cached."""
    cache = Path(tempfile.gettempdir()) / "edi-live-bench"
    cache.mkdir(exist_ok=True)
    path = cache / f"fast_{width}x{height}.aedat4"
    if not path.exists():
        from tools import simulate

        print(f"simulating {path.name} (once) ...", flush=True)
        cfg = simulate.preset("fast", width=width, height=height, duration_s=1.0, texture="blocks")
        sim = simulate.simulate(cfg)
        tmp = path.with_suffix(".part")
        simulate.write_aedat4(sim, tmp)
        tmp.replace(path)
    return path


def recording_stats(path: Path) -> tuple[int, int, int]:
    """(events, first t, last t) of a recording, via the replay merge."""
    from drivers.replay import merged_packets

    n, t0, t1 = 0, None, None
    for p in merged_packets(path):
        if len(p.events):
            n += len(p.events)
            t0 = int(p.events["t"][0]) if t0 is None else t0
            t1 = int(p.events["t"][-1])
    return n, t0 or 0, t1 or 0


class GatedSource:
    """Holds the first packet until `gate` is set (the subscriber is connected); records the first-packet time."""

    def __init__(self, inner, gate: threading.Event, max_loops: int | None = None) -> None:
        self.inner, self.gate, self.info = inner, gate, inner.info
        self.max_loops = max_loops  # with a looping replay: end after this many passes
        self.first_packet_s: float | None = None

    def __enter__(self):
        self.inner.__enter__()
        return self

    def __exit__(self, *exc):
        self.inner.__exit__(*exc)

    def stop(self):
        self.gate.set()
        self.inner.stop()

    def status(self):
        return self.inner.status()

    def __iter__(self):
        while not self.gate.wait(0.1):
            yield None
        for packet in self.inner:
            if self.first_packet_s is None and packet is not None:
                self.first_packet_s = time.perf_counter()
            if self.max_loops is not None and getattr(self.inner, "loops", 0) >= self.max_loops:
                return
            yield packet


def _replay(path: Path, speed: float, loop: bool = False, **options):
    import drivers

    # as the CLI opens it: decoded in a child process (see drivers/decoding_child.py)
    return drivers.open_source("replay", path=str(path), speed=speed, loop=loop, decode_process=True, **options)


# ------------------------------------------------------------------------------------------------ subscriber

def _subscriber(endpoint: str, conn) -> None:
    """Child process: receive every frame (no newest-only skipping), report count, seq gaps and timing."""
    from edi_live.client import Subscriber

    with Subscriber(endpoint, newest_only=False, rcvhwm=0, max_bytes=1 << 20) as sub:
        while sub.recv_stats(timeout_s=0.5) is None:  # the subscription is live once stats arrive
            pass
        conn.send("ready")
        cpu0 = time.process_time()
        n, first_s, last_s, seqs_ok, last_seq, gaps = 0, None, None, True, -1, 0
        arrivals: list[tuple[int, int, bool]] = []
        while True:
            got = sub.recv(timeout_s=2.0)
            if got is None:
                if conn.poll():
                    break
                continue
            header, _ = got
            now = time.perf_counter()
            # for the latency seen from outside: when it came, and the sensor time of its last event
            arrivals.append((time.monotonic_ns(), header["exp_end"] if header["kind"] == "deblurred" else header["t"],
                             header["kind"] == "deblurred"))
            first_s = first_s or now
            last_s = now
            if header["seq"] <= last_seq:
                seqs_ok = False
            gaps += max(0, header["seq"] - last_seq - 1) if last_seq >= 0 else 0
            last_seq = header["seq"]
            n += 1
        conn.send({"frames": n, "seq_increasing": seqs_ok, "seq_gaps": gaps,
                   "span_s": (last_s - first_s) if n > 1 else 0.0, "cpu_s": time.process_time() - cpu0,
                   "arrivals": np.array(arrivals, np.int64).reshape(-1, 3)})


class _RecordingPublisher:
    """A Publisher that also keeps every frame's latency (arrival of its last event -> sent), for percentiles."""

    def __new__(cls, **kwargs):
        from edi_live.publisher import Publisher

        class Recording(Publisher):
            def __init__(self, **kw):
                super().__init__(**kw)
                self.latencies_us: list[float] = []
                self.kinds: list[str] = []

            def _send_frame(self, sock, rec):
                sent_before = self._sent
                super()._send_frame(sock, rec)
                if self._sent > sent_before and rec.arrival_ns > 0:
                    self.latencies_us.append((time.monotonic_ns() - rec.arrival_ns) / 1e3)
                    self.kinds.append(rec.kind)

        return Recording(**kwargs)


def _lossless_publisher(**kwargs):
    # the benchmark measures what the node sustains when nothing is dropped: a deep inbox and no HWM
    return _RecordingPublisher(**kwargs, inbox_size=1 << 20, sndhwm=0)



def thread_cpu_seconds() -> dict[int, tuple[str, float]]:
    """{thread id: (OS thread name, user + system CPU seconds)} of this process (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[int, tuple[str, float]] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                head, rest = fh.read().rsplit(")", 1)
        except OSError:
            continue  # the thread ended meanwhile
        fields = rest.split()
        out[int(tid)] = (head.split("(", 1)[1], (int(fields[11]) + int(fields[12])) / tick)
    return out

class ThreadCpu:
    """Samples each named thread's CPU time from /proc (Linux), keeping the last value seen per thread."""

    def __init__(self, period_s: float = 0.1) -> None:
        self.cpu_s: dict[str, float] = {}  # by thread name (threads of the same name summed)
        self._per_thread: dict[str, float] = {}
        self._base: dict[str, float] = self._sample()
        self._stop = threading.Event()
        self._period_s = period_s
        self._thread = threading.Thread(target=self._run, name="cpu-sampler", daemon=True)

    def __enter__(self) -> "ThreadCpu":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(2)

    @staticmethod
    def _sample() -> dict[str, float]:
        """CPU s per thread of this process: Python threads by name, libzmq's I/O thread and others by OS name."""
        python_names = {t.native_id: t.name for t in threading.enumerate()}
        return {f"{python_names.get(tid, name)}/{tid}": cpu_s for tid, (name, cpu_s) in thread_cpu_seconds().items()}

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            for key, total_s in self._sample().items():
                self._base.setdefault(key, total_s)  # threads started meanwhile count from their first sample
                self._per_thread[key] = total_s - self._base[key]
            by_name: dict[str, float] = {}
            for key, v in self._per_thread.items():
                name = key.rsplit("/", 1)[0]
                by_name[name] = by_name.get(name, 0.0) + v
            self.cpu_s = by_name

    def split(self) -> str:
        keep = {k: v for k, v in self.cpu_s.items()
                if k in ("pump", "edi-worker", "publisher", "MainThread") or k.startswith("ZMQbg/IO")}
        total = sum(keep.values()) or 1.0
        return ", ".join(f"{k} {v:.2f} s ({100 * v / total:.0f}%)" for k, v in sorted(keep.items(),
                                                                                      key=lambda kv: -kv[1]))


def run_with_subscriber(path: Path, options: dict, speed: float, publisher_factory=_lossless_publisher,
                        passes: int | None = None, packet_us: int | None = None):
    cfg = NodeConfig.from_options({"replay": str(path), "speed": speed, "publish": ["tcp://127.0.0.1:*"],
                                   "stats_interval_s": 0.2, **options})
    gate = threading.Event()
    loop = passes is not None or bool(options.get("loop"))
    extra = {} if packet_us is None else {"max_packet_us": packet_us}
    source = GatedSource(_replay(path, speed, loop=loop, **extra), gate, max_loops=passes)
    node = Node(cfg, source, publisher_factory=publisher_factory)
    result: dict = {}

    def run():
        try:
            result["stats"] = node.run()
        except BaseException as exc:
            result["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    if not node.started.wait(30):
        raise SystemExit(f"node did not start: {result.get('error')}")
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_subscriber, args=(node.bound_endpoints[0], child), daemon=True)
    proc.start()
    if not parent.poll(30):
        raise SystemExit("subscriber did not connect")
    parent.recv()
    cpu0 = time.process_time()
    with ThreadCpu() as threads_cpu:
        gate.set()
        thread.join(600)
    end_s = time.perf_counter()
    cpu_s = time.process_time() - cpu0
    parent.send("stop")
    sub = parent.recv() if parent.poll(30) else {}
    proc.join(10)
    if "error" in result:
        raise SystemExit(f"node failed: {result['error']!r}")
    result["stats"]["node_cpu_s"] = cpu_s
    result["stats"]["thread_cpu"] = threads_cpu.split()
    return result["stats"], sub, (end_s - source.first_packet_s), node.publisher


# ------------------------------------------------------------------------------------------------ modes

def bench_throughput(path: Path, every: int, repeat: int, passes: int, extra: dict | None = None) -> None:
    n_events, t0, t1 = recording_stats(path)
    print(f"\n## throughput: replay --speed 0 -> worker -> publish -> 1 subscriber, --every {every}")
    print(f"input {path.name}: {n_events} events over {(t1 - t0) / 1e6:.2f} s of sensor time, replayed "
          f"{passes} times back to back (--loop)")
    rows = []
    for _ in range(repeat):
        stats, sub, wall_s, pub = run_with_subscriber(path, {"every": every, **(extra or {})}, speed=0,
                                                      passes=passes)
        rows.append((stats["events_processed"] / wall_s, sub.get("frames", 0) / wall_s, sub.get("frames", 0),
                     stats["frames_out"], stats["node_cpu_s"], wall_s, sub.get("seq_gaps"),
                     stats["events_processed"] / stats["node_cpu_s"]))
    ev_s, fr_s = float(np.median([r[0] for r in rows])), float(np.median([r[1] for r in rows]))
    per_cpu = float(np.median([r[7] for r in rows]))
    print("| run | events/s | frames/s received | frames received / emitted | node CPU s | wall s | seq gaps | "
          "events per node-CPU-s |")
    print("|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows):
        print(f"| {i} | {r[0] / 1e6:.2f} M | {r[1]:.0f} | {r[2]} / {r[3]} | {r[4]:.2f} | {r[5]:.2f} | {r[6]} | "
              f"{r[7] / 1e6:.2f} M |")
    print(f"median: {ev_s / 1e6:.2f} M events/s, {fr_s:.0f} frames/s wall-clock (target >= 12 M events/s, "
          f">= 12,000 frames/s); {per_cpu / 1e6:.2f} M events per CPU-second of the node process "
          f"(all its threads; the subscriber is another process)")
    print(f"CPU by thread (last run, while data flowed): {stats['thread_cpu']}; subscriber process "
          f"{sub.get('cpu_s', float('nan')):.2f} s ({1e6 * sub.get('cpu_s', float('nan')) / max(1, sub.get('frames', 1)):.0f}"
          f" µs per frame received)")
    print(f"best run: {max(r[0] for r in rows) / 1e6:.2f} M events/s (the machine is shared: the best run is the "
          f"one least disturbed by other jobs)")
    print(f"load average now: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")


def bench_latency(path: Path, every: int, rate_ev_s: float, seconds: float, packet_us: int = 1000,
                  extra: dict | None = None) -> None:
    n_events, t0, t1 = recording_stats(path)
    file_rate = n_events / max((t1 - t0) / 1e6, 1e-9)
    speed = rate_ev_s / file_rate
    print(f"\n## latency: paced replay at {rate_ev_s / 1e6:.2f} M events/s (file rate {file_rate / 1e6:.2f} M/s, "
          f"--speed {speed:.3f}), --every {every}, last-event arrival -> frame sent")
    options = {"every": every, "loop": seconds > (t1 - t0) / 1e6 / speed, "duration": seconds, **(extra or {})}
    print(f"node options: {options}")
    stats, sub, wall_s, pub = run_with_subscriber(path, options, speed=speed, packet_us=packet_us)
    lat = np.array(pub.latencies_us)
    if not len(lat):
        print("no frames")
        return
    p50, p90, p99, pmax = np.percentile(lat, [50, 90, 99, 100])
    print(f"APS deblur (on_frame until its frame is ready; with the deblur thread the level table and the c "
          f"decision come after, in settle) per frame: p50 {stats.get('deblur_ms_p50')} ms, max "
          f"{stats.get('deblur_ms_max')} ms; c re-estimations {stats.get('reestimations')}")
    print(f"frames {len(lat)}, received {sub.get('frames')}: latency p50 {p50 / 1000:.3f} ms, p90 {p90 / 1000:.3f} ms, "
          f"p99 {p99 / 1000:.3f} ms, max {pmax / 1000:.3f} ms (target p99 <= 1 ms)")
    kinds = np.array(pub.kinds)
    for kind in ("latent", "deblurred"):
        sel = lat[kinds == kind]
        if len(sel):
            q = np.percentile(sel, [50, 90, 99, 100]) / 1000
            print(f"  {kind:9s} frames {len(sel):6d}: p50 {q[0]:.3f} ms, p90 {q[1]:.3f} ms, p99 {q[2]:.3f} ms, "
                  f"max {q[3]:.3f} ms")
    _print_outside_latency(sub.get("arrivals"), speed)
    print(f"achieved event rate {stats['events_processed'] / wall_s / 1e6:.2f} M/s over {wall_s:.1f} s; replay "
          f"packets span up to {packet_us} µs of events (a USB-transfer-like cadence), so a packet's frames share "
          f"one arrival stamp; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")


def outside_latency_us(arrivals: np.ndarray, speed: float) -> np.ndarray:
    """Latency seen at the subscriber (µs): receive time minus the paced wall time of the frame's last event (for
    a deblurred frame its exposure end), relative to the fastest frame of each pass over the recording (the
    subscriber does not know when the replay clock started; a pass begins where sensor time jumps back)."""
    recv_ns, t_us = arrivals[:, 0].astype(np.float64), arrivals[:, 1].astype(np.float64)
    offset = recv_ns / 1e3 - t_us / speed  # paced: wall µs = start + (t - t0) / speed
    out = np.empty_like(offset)
    passes = np.flatnonzero(np.diff(t_us) < -2e5) + 1  # a loop restart: sensor time back by more than 0.2 s
    for seg in np.split(np.arange(offset.size), passes):
        if seg.size:
            out[seg] = offset[seg] - offset[seg].min()
    return out


def _print_outside_latency(arrivals: np.ndarray | None, speed: float) -> None:
    if arrivals is None or not len(arrivals):
        return
    lat = outside_latency_us(arrivals, speed) / 1000
    deblurred = arrivals[:, 2].astype(bool)
    print("seen from the subscriber (receive time - paced wall time of the frame's last event / exposure end, "
          "relative to the fastest frame of each pass):")
    for kind, sel in (("latent", ~deblurred), ("deblurred", deblurred)):
        if sel.any():
            q = np.percentile(lat[sel], [50, 90, 99, 100])
            print(f"  {kind:9s} frames {int(sel.sum()):6d}: p50 {q[0]:.3f} ms, p90 {q[1]:.3f} ms, p99 {q[2]:.3f} ms, "
                  f"max {q[3]:.3f} ms")


def bench_stages(path: Path, every: int, repeat: int, extra: dict | None = None) -> None:
    """CPU per stage, each run alone on one thread (thread_time: robust against other jobs on the machine).

    The sum is the CPU the pipeline needs per event; the GIL-held part of it bounds the end-to-end rate."""
    import drivers
    from edi_live.config import EdiConfig
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    print(f"\n## stages: CPU per stage, each alone on one thread, --every {every} ({path.name})")
    rows: dict[str, list[float]] = {"pump: replay decode + merge (per 1000 events)": [],
                                    "pump: ring push + worker's ring read (per 1000 events)": [],
                                    "worker: latent frames, EDI + worker (per frame)": [],
                                    "worker: APS deblur (per APS frame)": [],
                                    "publisher: encode + send to 1 subscriber (per frame)": []}
    n_frames = n_aps = n_events = 0
    for _ in range(repeat):
        # 1. replay decode + merge
        src = drivers.open_source("replay", path=str(path), speed=0)
        packets = []
        c0 = time.thread_time()
        with src:
            for packet in src:
                if packet is not None:
                    packets.append(packet)
        pump_s = time.thread_time() - c0
        n_events = sum(len(p.events) for p in packets)
        rows["pump: replay decode + merge (per 1000 events)"].append(pump_s / n_events * 1e9)
        # 2. ring push + read (the read is the worker's part, done here on the same thread)
        ring = EventRing(1 << 23, 1 << 10, "wait")
        c0 = time.thread_time()
        for packet in packets:
            ring.push(packet)
        ring.close()
        push_s = time.thread_time() - c0
        probe = EventRing(1 << 23, 1 << 10, "wait")
        for packet in packets:
            probe.push(packet)
        c0 = time.thread_time()
        while len(probe.read_events(1 << 16).events) or probe.pop_frame() is not None:
            pass  # (a read stops at each queued frame's exposure end, as the worker's does)
        read_s = time.thread_time() - c0
        rows["pump: ring push + worker's ring read (per 1000 events)"].append((push_s + read_s) / n_events * 1e9)
        # 3. worker on the filled ring, synchronously, sink collecting frames
        out: list = []
        cfg = EdiConfig(every=every, deblur_thread=False, **(extra or {}))
        worker = EdiWorker(ring, default_reconstructor(src.info.width, src.info.height, cfg), cfg, [out.append])
        c0 = time.thread_time()
        worker._run()
        work_s = time.thread_time() - c0
        if worker.error is not None:
            raise SystemExit(f"worker failed: {worker.error!r}")
        deblur_s = sum(worker._deblur_ms) / 1e3
        n_aps = len(worker._deblur_ms)
        n_frames = len(out)
        rows["worker: latent frames, EDI + worker (per frame)"].append((work_s - deblur_s) / max(1, n_frames - n_aps)
                                                                       * 1e6)
        rows["worker: APS deblur (per APS frame)"].append(deblur_s / max(1, n_aps) * 1e6)
        # 4. publisher: submit every frame to a publisher with one subscriber process receiving all
        rows["publisher: encode + send to 1 subscriber (per frame)"].append(_publish_cpu_per_frame(out) * 1e6)
    print(f"{n_events} events, {n_frames} frames ({n_aps} APS deblurs); medians of {repeat}")
    print("| stage | CPU µs | per 1000 events (µs) |\n|---|---|---|")
    total = 0.0
    for name, values in rows.items():
        v = float(np.median(values))
        if "per 1000 events" in name:
            per_k = v
        elif "APS" in name:
            per_k = v * n_aps / n_events * 1000
        elif "latent" in name:
            per_k = v * (n_frames - n_aps) / n_events * 1000
        else:
            per_k = v * n_frames / n_events * 1000
        total += per_k
        print(f"| {name} | {v:.1f} | {per_k:.1f} |")
    print(f"| total | | {total:.1f} |")
    print(f"=> one core running everything: {1e3 / total:.2f} M events/s; 12 M events/s needs <= 83 µs per 1000 "
          f"events across the node's threads (and the GIL-held part of it on one core)")


def _publish_cpu_per_frame(recs: list) -> float:
    from edi_live.publisher import Publisher

    pub = Publisher(["tcp://127.0.0.1:*"], "bench", inbox_size=1 << 20, sndhwm=0)
    pub.start()
    try:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_subscriber, args=(pub.bound_endpoints[0], child), daemon=True)
        proc.start()
        while not parent.poll(0.05):  # the subscriber reports ready once it receives a stats message
            pub.submit(recs[0])
        parent.recv()
        sent0 = pub.stats()["sent"]
        c0 = time.process_time()
        for rec in recs:
            pub.submit(rec)
        deadline = time.monotonic() + 60
        while pub.stats()["sent"] < sent0 + len(recs) and time.monotonic() < deadline:
            time.sleep(0.0005)
        cpu_s = time.process_time() - c0
        time.sleep(0.2)
        parent.send("stop")
        parent.poll(30)
        proc.join(10)
    finally:
        pub.close()
    return cpu_s / len(recs)


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
    node = Node(cfg, _replay(path, speed, loop=True))
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


def noisy_scene(seconds: float, onset_s: float | None = None, noise_hz: float = 0.5, width: int = 240,
                height: int = 180, speed_px_s: float = 100.0) -> tuple[np.ndarray, list, int | None]:
    """A still camera with `noise_hz` background events per pixel and APS frames at 20 fps (simulated), and,
    with `onset_s`, the scene starts moving (`speed_px_s`) at that time. Returns (events, frames, the sensor
    time of the first event caused by motion or None)."""
    from edi_live.simulation import SceneConfig, simulate

    base = dict(width=width, height=height, noise_rate_hz=noise_hz, frame_interval_us=50_000, exposure_us=10_000,
                ground_truth=False, texture="blocks")
    still = simulate(SceneConfig(duration_s=onset_s or seconds, velocity_px_s=(0.0, 0.0), **base))
    if onset_s is None:
        return still.events, still.frames, None
    # the moving part starts from the same picture (position = v * t from its own t0), one frame period later
    moving = simulate(SceneConfig(duration_s=seconds - onset_s, velocity_px_s=(speed_px_s, 0.0),
                                  t0_us=still.config.t0_us + int(onset_s * 1e6), **base))
    events = np.concatenate([still.events, moving.events])
    return events, still.frames + moving.frames, int(moving.events["t"][~moving.is_noise][0])


def scene_packets(events: np.ndarray, frames: list, packet_us: int = 1000) -> list[Packet]:
    """1 ms packets as a camera delivers them; each APS frame in the packet that holds its exposure end."""
    t0, t1 = int(events["t"][0]), int(events["t"][-1])
    bounds = np.arange(t0, t1 + packet_us, packet_us)
    cuts = np.searchsorted(events["t"], bounds, side="right")
    packets, k = [], 0
    for i in range(len(bounds)):
        lo = cuts[i - 1] if i else 0
        mine = []
        while k < len(frames) and frames[k].exposure_end_us <= bounds[i]:
            mine.append(frames[k])
            k += 1
        packets.append(Packet(events=events[lo:cuts[i]], frames=mine, watermark_us=int(bounds[i])))
    return packets


class CountOnlyPolicy:
    """The static-scene policy before the noise test (every event counts as activity), for A/B runs."""

    def __enter__(self):
        from edi_live.activity import StaticScene

        self._saved = StaticScene.segments, StaticScene.active_since_reference, StaticScene.quiet
        StaticScene.segments = lambda scene, events: [(0, len(events), "active")] if len(events) else []
        StaticScene.active_since_reference = lambda scene: True
        StaticScene.quiet = property(lambda scene: False)  # every read as it comes, as then
        return self

    def __exit__(self, *exc):
        from edi_live.activity import StaticScene

        StaticScene.segments, StaticScene.active_since_reference, StaticScene.quiet = self._saved


def noise_recording(seconds: float, noise_hz: float = 0.5) -> Path:
    """The still noisy scene of `noisy_scene` as an AEDAT4 recording, generated once and cached."""
    cache = Path(tempfile.gettempdir()) / "edi-live-bench"
    cache.mkdir(exist_ok=True)
    path = cache / (f"noise_static_{seconds:.0f}s.aedat4" if noise_hz == 0.5 else
                    f"noise_static_{seconds:.0f}s_{noise_hz:g}hz.aedat4")
    if not path.exists():
        from edi_live.aedat4 import Aedat4Writer

        events, frames, _ = noisy_scene(seconds, noise_hz=noise_hz)
        tmp = path.with_suffix(".part")
        with Aedat4Writer(tmp, 240, 180) as writer:
            for p in scene_packets(events, frames, packet_us=10_000):
                writer.write_events(p.events)
                for f in p.frames:
                    writer.write_frame(f)
        tmp.replace(path)
    return path


def bench_noise(seconds: float, repeat: int) -> None:
    print(f"\n## static 240x180 scene with 0.5 events/s per pixel of noise, APS at 20 fps: paced replay (speed 1) "
          f"with the publisher, {seconds:.0f} s measured after 2 s; node process CPU (the decoding child, the same in "
          f"both, not counted); A/B interleaved, {repeat} repeats")

    path = noise_recording(seconds + 4)
    results: dict[str, list] = {"count-only (before)": [], "noise-aware": []}
    for _ in range(repeat):
        for name in results:
            with (CountOnlyPolicy() if name.startswith("count") else _Nothing()):
                cfg = NodeConfig.from_options({"replay": str(path), "publish": ["tcp://127.0.0.1:*"]})
                node = Node(cfg, _replay(path, 1.0))
                thread = threading.Thread(target=node.run, daemon=True)
                thread.start()
                node.started.wait(30)
                time.sleep(2.0)
                s0, cpu0, wall0 = node.stats(), time.process_time(), time.monotonic()
                with ThreadCpu() as threads:
                    time.sleep(seconds)
                cpu, wall, s1 = time.process_time() - cpu0, time.monotonic() - wall0, node.stats()
                node_cpu = threads.cpu_s.get("edi-worker", 0.0) + threads.cpu_s.get("publisher", 0.0)
                node.stop()
                thread.join(30)
            d = {k: s1[k] - s0[k] for k in ("frames_out", "heartbeats", "aps_frames_in", "skipped_static_deblur")}
            results[name].append((100 * node_cpu / wall, 100 * cpu / wall, (d["frames_out"] - d["heartbeats"]) / wall,
                                  d["heartbeats"] / wall, (d["aps_frames_in"] - d["skipped_static_deblur"]) / wall))
    print("| policy | worker + publisher, % of one core, median (min-max) | whole process (with the replay's pump) | "
          "non-heartbeat frames/s | heartbeats/s | deblurs/s |\n|---|---|---|---|---|---|")
    for name, rows in results.items():
        a = np.array(rows)
        print(f"| {name} | {np.median(a[:, 0]):.1f} ({a[:, 0].min():.1f}-{a[:, 0].max():.1f}) | "
              f"{np.median(a[:, 1]):.1f} ({a[:, 1].min():.1f}-{a[:, 1].max():.1f}) | "
              f"{np.median(a[:, 2]):.1f} | {np.median(a[:, 3]):.2f} | {np.median(a[:, 4]):.2f} |")
    print("\nmotion onset (the scene starts moving at 100 px/s after 1 s; worker alone, 1 ms packets in lockstep): "
          "first moving event -> sensor time the ring had reached when the first frame after it was sent")
    for k in range(repeat):
        delay = onset_delay_us(seed_shift=k)
        print(f"  run {k}: {delay / 1000:.1f} ms (APS frame period 50 ms)")


_NOISE_CHILD = r"""
import json, os, sys, threading, time
import drivers
from edi_live.config import NodeConfig
from edi_live.node import Node


def threads_cpu():
    tick, names, out = os.sysconf("SC_CLK_TCK"), {t.native_id: t.name for t in threading.enumerate()}, {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                head, rest = fh.read().rsplit(")", 1)
        except OSError:
            continue
        fields, name = rest.split(), names.get(int(tid), head.split("(", 1)[1])
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


if __name__ == "__main__":
    path, seconds = sys.argv[1], float(sys.argv[2])
    cfg = NodeConfig.from_options({"replay": path, "publish": ["tcp://127.0.0.1:*"]})
    node = Node(cfg, drivers.open_source("replay", path=path, speed=1.0, decode_process=True))
    thread = threading.Thread(target=node.run, daemon=True)
    thread.start()
    node.started.wait(60)
    time.sleep(2.0)
    s0, t0, cpu0, wall0 = node.stats(), threads_cpu(), time.process_time(), time.monotonic()
    time.sleep(seconds)
    cpu, wall, t1, s1 = time.process_time() - cpu0, time.monotonic() - wall0, threads_cpu(), node.stats()
    node.stop()
    thread.join(30)
    d = {k: s1[k] - s0[k] for k in ("frames_out", "heartbeats", "aps_frames_in", "skipped_static_deblur")}
    by = {k: v - t0.get(k, 0.0) for k, v in t1.items()}
    print(json.dumps({"node": 100 * (by.get("edi-worker", 0) + by.get("publisher", 0)) / wall,
                      "pump": 100 * by.get("pump", 0) / wall, "process": 100 * cpu / wall,
                      "no_pump": 100 * (cpu - by.get("pump", 0)) / wall,
                      "frames": (d["frames_out"] - d["heartbeats"]) / wall, "heartbeats": d["heartbeats"] / wall,
                      "deblurs": (d["aps_frames_in"] - d["skipped_static_deblur"]) / wall}))
"""


def bench_noise_ab(seconds: float, repeat: int, other: Path) -> None:
    """The node on the noisy still scene, this checkout against `other`, each run in its own process (which imports
    that checkout's code), in alternating order; per-thread CPU from /proc at the start and end of the window."""
    import json
    import subprocess

    here = Path(__file__).resolve().parent.parent
    path = noise_recording(seconds + 4)
    print(f"\n## A/B: static 240x180 scene, 0.5 events/s per pixel of noise, APS 20 fps, paced replay (speed 1) with "
          f"the publisher, {seconds:.0f} s after 2 s; new = {here}, old = {other}; {repeat} pairs, alternating order")
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    for i in range(repeat):
        for which in (("old", "new") if i % 2 == 0 else ("new", "old")):
            out = subprocess.run([sys.executable, "-c", _NOISE_CHILD, str(path), str(seconds)],
                                 cwd=other if which == "old" else here, capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(f"{which} run failed:\n{out.stderr[-2000:]}")
            runs[which].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| checkout | worker + publisher, % of one core | process without the pump | pump | whole process | "
          "non-heartbeat frames/s | heartbeats/s | deblurs/s |\n|---|---|---|---|---|---|---|---|")
    for which, rows in runs.items():
        def cell(key: str, digits: int = 1) -> str:
            v = np.array([r[key] for r in rows])
            return f"{np.median(v):.{digits}f} ({v.min():.{digits}f}-{v.max():.{digits}f})"
        print(f"| {which} | {cell('node', 2)} | {cell('no_pump', 2)} | {cell('pump')} | {cell('process')} | "
              f"{cell('frames')} | "
              f"{cell('heartbeats', 2)} | {cell('deblurs', 2)} |")
    for key in ("node", "no_pump", "process"):
        ratios = [o[key] / max(n[key], 1e-9) for o, n in zip(runs["old"], runs["new"])]
        print(f"old / new, {key} CPU per pair: median {np.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})")
    print("(thread CPU is counted in 10 ms ticks, so read the thread figures to +-0.1 % of a core; the deblur "
          "helper threads of the 1/s heartbeat deblur end within the window: they are in the process figures only)")


class _Nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def onset_delay_us(seed_shift: int = 0, every: int = 1000, ring=None, clock_offset_us: int | None = None) -> float:
    """Worker alone (real reconstructor) fed 1 ms packets in lockstep, as a camera delivers them: each is pushed
    once the worker has done all it will do with the ones before (EventRing.wait_consumer_idle), so what it sees
    per wake-up is what it would see live, however fast this machine is. Returns the sensor time from the first
    event caused by motion to the newest data in the ring when the first frame after it was sent (not the first
    deblurred frame; the heartbeat is off), i.e. the onset delay without the host's processing time.
    `clock_offset_us`: a fixed event clock offset (default: estimated), e.g. a real camera's few ms that each
    APS frame waits for its late events."""
    from edi_live.config import EdiConfig
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    events, frames, onset = noisy_scene(1.0 + 0.3, onset_s=1.0 + 0.01 * seed_shift)
    ring = ring if ring is not None else EventRing(capacity_events=1 << 22, capacity_frames=256, policy="wait")
    sent: list = []
    worker = EdiWorker(ring, default_reconstructor(240, 180, EdiConfig(clock_offset_us=clock_offset_us)),
                       EdiConfig(every=every, heartbeat_s=3600),
                       [lambda r: sent.append((r.t_us, ring.watermark_us))])
    worker.start()
    try:
        for p in scene_packets(events, frames):
            ring.push(p)
            if not ring.wait_consumer_idle(60):
                raise RuntimeError(f"the worker did not settle (error: {worker.error!r})")
    finally:
        ring.close()
        worker.done.wait(60)
    if worker.error is not None:
        raise RuntimeError(f"worker failed: {worker.error!r}")
    assert worker.events_in == len(events), "every event was read"
    early = [t for t, _ in sent[1:] if t < onset]
    assert not early, f"frames on the static part: {early}"
    later = [newest for t, newest in sent[1:] if t >= onset]
    return (later[0] - onset) if later else float("inf")


def bench_scaling(every: int, repeat: int) -> None:
    print(f"\n## scaling: one latent frame (on_events of {every} events + render) vs changed pixels and resolution")
    from edi_live.config import EdiConfig

    rng = np.random.default_rng(1)
    print("| resolution | changed pixels | µs per frame (median) | of which render µs |\n|---|---|---|---|")
    for w, h in ((240, 180), (346, 260), (640, 480), (1280, 720)):
        rec = default_reconstructor(w, h, EdiConfig(c=0.2))
        img = rng.integers(20, 235, (h, w)).astype(np.uint8)
        ev0 = np.zeros(0, EVENT_DTYPE)
        rec.on_frame(Frame(img, exposure_start_us=0, exposure_end_us=10_000), ev0)
        t_us = 10_000
        for k in (10, 100, 1000):
            k = min(k, w * h)
            pix = rng.choice(w * h, k, replace=False)
            times, render_times = [], []
            for _ in range(repeat * 20):
                ev = np.zeros(every, EVENT_DTYPE)
                ev["t"] = t_us + np.arange(every)
                t_us += every
                sel = pix[rng.integers(0, k, every)]
                ev["x"], ev["y"] = sel % w, sel // w
                ev["p"] = rng.integers(0, 2, every).astype(bool)
                a = time.perf_counter()
                rec.on_events(ev)
                b = time.perf_counter()
                rec.render()
                c = time.perf_counter()
                times.append(c - a)
                render_times.append(c - b)
            print(f"| {w}x{h} | {k} | {1e6 * np.median(times):.1f} | {1e6 * np.median(render_times):.1f} |")


def _extra(args: argparse.Namespace) -> dict:
    extra: dict = {}
    if args.c is not None:
        extra["c"] = args.c
    if args.no_deblur_thread:
        extra["deblur_thread"] = False
    if args.no_deblur_ahead:
        extra["deblur_ahead"] = False
    if args.clock_offset_us is not None:
        extra["clock_offset_us"] = args.clock_offset_us
    return extra


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_stream", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("throughput", "stages", "latency", "memory", "static", "noise", "scaling",
                                     "all"))
    ap.add_argument("--input", type=Path, help="an .aedat4 recording (default: simulated 240x180, cached)")
    ap.add_argument("--every", type=int, default=1000, help="events per latent frame (default 1000)")
    ap.add_argument("--repeat", type=int, default=3, help="runs for medians (default 3)")
    ap.add_argument("--passes", type=int, default=5, help="throughput: passes over the recording (default 5)")
    ap.add_argument("--rate", type=float, default=1e6, help="latency mode: paced event rate, events/s (default 1e6)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="memory: run length (default 60; use 600 for the 10-minute run); latency/static: 10")
    ap.add_argument("--c", type=float, help="throughput/latency: fixed contrast threshold (default: estimated)")
    ap.add_argument("--no-deblur-ahead", action="store_true",
                    help="throughput/latency: read each exposure's events at its end (the node's deblur-ahead = false)")
    ap.add_argument("--clock-offset-us", type=int, default=None,
                    help="throughput/latency: give the event clock offset instead of estimating it")
    ap.add_argument("--no-deblur-thread", action="store_true",
                    help="throughput/latency: deblur APS frames on the worker thread (the node's deblur-thread = false)")
    ap.add_argument("--speed", type=float, default=1.0, help="memory mode: replay speed (default 1 = real time)")
    ap.add_argument("--against", type=Path, default=None,
                    help="noise mode: A/B against another checkout (e.g. ../main), each run in its own process")
    args = ap.parse_args(argv)
    path = args.input
    if args.mode in ("throughput", "stages", "latency", "memory", "all") and path is None:
        path = default_recording()
    print(f"machine: {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, numpy {np.__version__}")
    if args.mode in ("throughput", "all"):
        bench_throughput(path, args.every, args.repeat, args.passes, extra=_extra(args))
    if args.mode in ("stages", "all"):
        bench_stages(path, args.every, args.repeat, extra={"c": args.c} if args.c is not None else None)
    if args.mode in ("latency", "all"):
        bench_latency(path, args.every, args.rate, args.seconds or 10.0, extra=_extra(args))
    if args.mode in ("static", "all"):
        bench_static(args.seconds or 10.0)
    if args.mode in ("noise", "all") and args.against is not None:
        bench_noise_ab(args.seconds or 20.0, args.repeat, args.against.resolve())
    elif args.mode in ("noise", "all"):
        bench_noise(args.seconds or 20.0, args.repeat)
    if args.mode in ("scaling", "all"):
        bench_scaling(args.every, args.repeat)
    if args.mode in ("memory", "all"):
        bench_memory(path, args.every, args.seconds or 60.0, args.speed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
