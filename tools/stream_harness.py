"""The full node as the streaming benchmarks run it (tools/bench_stream.py and the tools that measure the node the
same way): its inputs (a simulated recording generated once and cached, a replay decoded in a child process as
the CLI opens it, a source that holds its first packet until the subscriber is connected), the subscriber process
that receives every frame, and run_with_subscriber, which runs the node with one such subscriber."""

from __future__ import annotations

import multiprocessing as mp
import tempfile
import threading
import time
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path

import numpy as np

from edi_live.config import NodeConfig
from edi_live.node import Node
from tools.thread_cpu import ThreadCpu


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


def replay_source(path: Path, speed: float, loop: bool = False, **options):
    import drivers

    # as the CLI opens it: decoded in a child process (see drivers/decoding_child.py)
    return drivers.open_source("replay", path=str(path), speed=speed, loop=loop, decode_process=True, **options)


def subscriber_child(endpoint: str, conn) -> None:
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


def start_subscriber(endpoint: str, timeout_s: float = 30.0) -> tuple[BaseProcess, Connection]:
    """subscriber_child in a spawned process, once its subscription is live: (the process, the parent's pipe end)."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=subscriber_child, args=(endpoint, child), daemon=True)
    proc.start()
    if not parent.poll(timeout_s):
        raise SystemExit("subscriber did not connect")
    parent.recv()
    return proc, parent


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


def run_with_subscriber(path: Path, options: dict, speed: float, publisher_factory=_lossless_publisher,
                        passes: int | None = None, packet_us: int | None = None):
    cfg = NodeConfig.from_options({"replay": str(path), "speed": speed, "publish": ["tcp://127.0.0.1:*"],
                                   "stats_interval_s": 0.2, **options})
    gate = threading.Event()
    loop = passes is not None or bool(options.get("loop"))
    extra = {} if packet_us is None else {"max_packet_us": packet_us}
    source = GatedSource(replay_source(path, speed, loop=loop, **extra), gate, max_loops=passes)
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
    proc, parent = start_subscriber(node.bound_endpoints[0])
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
