"""How many wire-protocol frames per second ZeroMQ carries to one subscriber that receives everything.

The subscriber runs in its own process and uses edi_live.client.Subscriber (so it validates and decodes every
message, as a real client does). Two publisher sides are measured:
  raw        a bare PUB socket sending wire.encode_frame() parts (the transport's ceiling)
  publisher  edi_live.publisher.Publisher.submit() (its inbox and thread included); the bench waits while the
             inbox is half full so that nothing is dropped, which a real node never does
Lossless: SNDHWM = RCVHWM = 0, and a readiness handshake so the slow-joiner effect loses nothing.

    python -m tools.bench_zmq                      # 240x180 u1, 20,000 frames, 5 runs, every combination
    python -m tools.bench_zmq --size 346x260 --runs 3 --mode raw --latency-fps 0
It also measures one-way latency (Publisher.submit -> decoded in the subscriber process) at a paced rate.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import time

import numpy as np

from edi_live import wire
from edi_live.datatypes import Reconstruction

WARMUP_T = -1


def make_rec(t_us: int, width: int, height: int, image: np.ndarray) -> Reconstruction:
    return Reconstruction(image, t_us, "latent", 0, 0, 0, 0.2, 0.2, 1000)


def bare_receiver(endpoint: str):
    """A plain SUB socket that reads only the header's time: the transport without client-side checks."""
    import msgpack
    import zmq

    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.RCVHWM, 0)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"frame")
    sock.connect(endpoint)

    def recv(timeout_s: float):
        try:
            parts = sock.recv_multipart(flags=zmq.NOBLOCK, copy=False)
        except zmq.Again:
            if not sock.poll(int(timeout_s * 1000)):
                return None
            parts = sock.recv_multipart(copy=False)
        return msgpack.unpackb(parts[1].bytes), parts[2]

    return recv, lambda: ctx.destroy(linger=0)


def client_receiver(endpoint: str):
    from edi_live.client import Subscriber

    sub = Subscriber(endpoint, newest_only=False, rcvhwm=0, max_bytes=1 << 20, stats=False)
    return sub.recv, sub.close


def subscriber(endpoint: str, n: int, ready, result, kind: str) -> None:
    recv, close = (client_receiver if kind == "client" else bare_receiver)(endpoint)
    try:
        first = last = None
        got = 0
        deadline = time.monotonic() + 60
        while got < n and time.monotonic() < deadline:
            item = recv(1.0)
            if item is None:
                continue
            header = item[0]
            if header["t"] == WARMUP_T:
                ready.set()
                continue
            last = time.perf_counter()
            first = first or last
            got += 1
    finally:
        close()
    elapsed = (last - first) if got > 1 else float("nan")
    result.put((got, elapsed))


def publish_raw(endpoint_holder, n: int, image: np.ndarray, ready, start_sub) -> None:
    import zmq

    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    sock.setsockopt(zmq.SNDHWM, 0)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind("tcp://127.0.0.1:*")
    proc = start_sub(sock.getsockopt_string(zmq.LAST_ENDPOINT))
    h, w = image.shape
    while not ready.wait(0.01):
        sock.send_multipart(wire.encode_frame(make_rec(WARMUP_T, w, h, image), 0, "bench"), copy=False)
    for i in range(n):
        sock.send_multipart(wire.encode_frame(make_rec(i, w, h, image), i, "bench"), copy=False)
    proc.join(90)
    sock.close(linger=0)
    ctx.term()


def publish_node(endpoint_holder, n: int, image: np.ndarray, ready, start_sub) -> None:
    from edi_live.publisher import Publisher

    pub = Publisher(["tcp://127.0.0.1:*"], "bench", sndhwm=0, inbox_size=1024)
    pub.start()
    proc = start_sub(pub.bound_endpoints[0])
    h, w = image.shape
    while not ready.wait(0.01):
        pub.submit(make_rec(WARMUP_T, w, h, image))
    for i in range(n):
        while pub.pending() >= 512:
            time.sleep(50e-6)
        pub.submit(make_rec(i, w, h, image))
    proc.join(90)
    dropped = pub.stats()["dropped"]
    pub.close()
    if dropped:
        print(f"  (publisher dropped {dropped})")


def latency_subscriber(endpoint: str, n: int, ready, result) -> None:
    """Receives frames whose `t` is the publisher's time.monotonic_ns() // 1000; records the one-way age."""
    from edi_live.client import Subscriber

    ages_us = []
    with Subscriber(endpoint, newest_only=False, rcvhwm=0, max_bytes=1 << 20, stats=False) as sub:
        deadline = time.monotonic() + 60
        while len(ages_us) < n and time.monotonic() < deadline:
            item = sub.recv(1.0)
            if item is None:
                continue
            now_us = time.monotonic_ns() // 1000
            if item[0]["n_events"] == 0:  # warm-up
                ready.set()
                continue
            ages_us.append(now_us - item[0]["t"])
    result.put(ages_us)


def latency_run(fps: float, seconds: float, image: np.ndarray) -> list[int]:
    """Paced Publisher.submit() at `fps`; one-way latency submit -> decoded in the subscriber process."""
    from edi_live.publisher import Publisher

    ctx = mp.get_context("spawn")
    ready, result = ctx.Event(), ctx.Queue()
    n = int(fps * seconds)
    pub = Publisher(["tcp://127.0.0.1:*"], "bench")
    pub.start()
    proc = ctx.Process(target=latency_subscriber, args=(pub.bound_endpoints[0], n, ready, result), daemon=True)
    proc.start()
    while not ready.wait(0.01):
        pub.submit(Reconstruction(image, 0, "latent", 0, 0, 0, 0.2, 0.2, 0))
    t0 = time.monotonic()
    for i in range(n):
        while time.monotonic() < t0 + i / fps:
            time.sleep(min(0.0005, max(0.0, t0 + i / fps - time.monotonic())))
        pub.submit(Reconstruction(image, time.monotonic_ns() // 1000, "latent", 0, 0, 0, 0.2, 0.2, 1))
    ages = result.get(timeout=90)
    proc.join(10)
    pub.close()
    return ages


def one_run(mode: str, n: int, image: np.ndarray, kind: str) -> tuple[int, float]:
    ctx = mp.get_context("spawn")
    ready, result = ctx.Event(), ctx.Queue()

    def start_sub(endpoint: str):
        proc = ctx.Process(target=subscriber, args=(endpoint, n, ready, result, kind), daemon=True)
        proc.start()
        return proc

    (publish_raw if mode == "raw" else publish_node)(None, n, image, ready, start_sub)
    return result.get(timeout=90)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="240x180", help="WxH of the u1 frames (default 240x180)")
    parser.add_argument("--frames", type=int, default=20_000, help="frames per run (default 20000)")
    parser.add_argument("--runs", type=int, default=5, help="runs per mode (default 5)")
    parser.add_argument("--mode", choices=["raw", "publisher", "both"], default="both")
    parser.add_argument("--subscriber", choices=["client", "bare", "both"], default="both",
                        help="client = edi_live.client.Subscriber (validates every message); bare = a plain "
                             "SUB socket reading only the header (default: both)")
    parser.add_argument("--latency-fps", type=float, default=1000.0,
                        help="also measure one-way latency at this paced frame rate (0 = skip; default 1000)")
    parser.add_argument("--latency-s", type=float, default=3.0, help="seconds of paced frames (default 3)")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    image = np.random.default_rng(0).integers(0, 256, size=(h, w), dtype=np.uint8)
    print(f"{w}x{h} u1 ({w * h} B) frames, {args.frames} per run, tcp://127.0.0.1, one subscriber process "
          f"receiving everything; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    kinds = ["bare", "client"] if args.subscriber == "both" else [args.subscriber]
    for mode in (["raw", "publisher"] if args.mode == "both" else [args.mode]):
        for kind in kinds:
            rates = []
            for _ in range(args.runs):
                got, elapsed = one_run(mode, args.frames, image, kind)
                if got < args.frames:
                    print(f"  {mode}/{kind}: only {got} of {args.frames} frames arrived")
                rates.append((got - 1) / elapsed)
            med = statistics.median(rates)
            print(f"{mode:>9} -> {kind:<6}: median {med:,.0f} frames/s = {med * w * h / 1e9:.2f} GB/s "
                  f"(runs {min(rates):,.0f}-{max(rates):,.0f})")
    if args.latency_fps > 0:
        ages = np.array(latency_run(args.latency_fps, args.latency_s, image))
        p50, p99 = np.percentile(ages, [50, 99])
        print(f"latency at {args.latency_fps:.0f} fps paced, Publisher.submit -> client decoded: "
              f"p50 {p50:.0f} us, p99 {p99:.0f} us, max {ages.max():.0f} us ({len(ages)} frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
