"""Benchmark: DAVIS USB word decode throughput (drivers.davis.decoder), and what numba buys.

Builds word streams with the project's encoder, cuts them into 128 KiB USB-sized chunks and times
`DavisDecoder.decode` over all chunks on one thread ("decoder": the numba kernel plus the APS/IMU state machine),
then the kernel's vectorised numpy reference alone (`_kernel.scan_numpy`, "numpy-ref": what the hot loop would
cost without numba). Prints the median of several runs in M events/s and
M words/s. Streams: "real" = the events of a real DAVIS346 recording (row bursts as a sensor produces them),
tiled in time; "uniform" = uniformly random addresses (worst case, ~1 timestamp word per event);
"+aps+imu" = real events plus 25 fps DAVIS346 APS frames and 1 kHz IMU samples. "x real time" = seconds of
sensor time decoded per second of wall time.

    python -m tools.bench_usb_decode [--events 4000000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from drivers.davis import _kernel
from drivers.davis.decoder import DavisDecoder
from drivers.davis.encoder import WordEncoder
from edi_live.datatypes import Frame

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real" / "emlb_demo-01_davis346.aedat4"
CHUNK_BYTES = 128 << 10


def real_events(n: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    try:
        from drivers.replay import merged_packets
        ev = np.concatenate([p.events for p in merged_packets(REAL)])
    except Exception as exc:  # noqa: BLE001 - fall back to synthetic bursts if the recording is unavailable
        print(f"(real recording unavailable: {exc}; using synthetic row bursts)")
        return uniform_events(n, rng, burst=8)
    t = ev["t"] - ev["t"][0]
    span = int(t[-1]) + 1
    reps = -(-n // len(ev))
    tt = np.concatenate([t + k * span for k in range(reps)])[:n]
    return tt, np.tile(ev["x"], reps)[:n], np.tile(ev["y"], reps)[:n], np.tile(ev["p"], reps)[:n]


def uniform_events(n: int, rng: np.random.Generator, burst: int = 1) -> tuple[np.ndarray, ...]:
    t = np.sort(rng.integers(0, n // 4 + 1, n // burst)).repeat(burst)[:n]  # ~4 M events/s of device time
    y = rng.integers(0, 260, n // burst).repeat(burst)[:n]
    return t, rng.integers(0, 346, len(t)), y, rng.random(len(t)) < 0.5


def encode(t, x, y, p, with_aps: bool) -> np.ndarray:
    enc = WordEncoder(346, 260)
    if not with_aps:
        return enc.encode_events(t, x, y, p)
    rng = np.random.default_rng(1)
    parts, pos = [], 0
    img = rng.integers(0, 256, (260, 346)).astype(np.uint8)
    for ms in range(0, int(t[-1]) // 1000):
        k = int(np.searchsorted(t, ms * 1000 + 999, side="right"))
        parts.append(enc.encode_events(t[pos:k], x[pos:k], y[pos:k], p[pos:k]))
        pos = k
        now = max(ms * 1000 + 999, enc.last_t)
        parts.append(enc.encode_imu(now, [0, -1, 0], [1, 2, 3], 30.0))
        if ms % 40 == 0:
            f = Frame(img, now, now)
            parts += [enc.encode_frame_start(now, f), enc.encode_frame_end(now, f)]
    parts.append(enc.encode_events(t[pos:], x[pos:], y[pos:], p[pos:]))
    return np.concatenate(parts)


def run(data: bytes, repeats: int) -> tuple[float, int, int, float]:
    chunks = [data[i:i + CHUNK_BYTES] for i in range(0, len(data), CHUNK_BYTES)]
    times, n_ev = [], 0
    for _ in range(repeats):
        d = DavisDecoder(346, 260)
        t0 = time.perf_counter()
        n_ev = sum(len(d.decode(c).events) for c in chunks)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), n_ev, len(data) // 2, d.watermark_us / 1e6


def run_numpy_reference(data: bytes, repeats: int) -> tuple[float, int, int, float]:
    """The kernel's numpy reference over the same chunks (events and timestamps only; chunks are even-sized)."""
    chunks = [np.frombuffer(data[i:i + CHUNK_BYTES], "<u2") for i in range(0, len(data), CHUNK_BYTES)]
    times, n_ev = [], 0
    for _ in range(repeats):
        state = _kernel.new_state(0)
        t0 = time.perf_counter()
        n_ev = sum(len(_kernel.scan_numpy(c, state, 346, 260, False)[0]) for c in chunks)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), n_ev, len(data) // 2, int(state[_kernel.S_CURRENT]) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=4_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    DavisDecoder(346, 260).decode(encode(*uniform_events(1000, rng), False).tobytes())  # compile outside the timing
    streams = {
        "real": encode(*real_events(args.events, rng), False),
        "uniform": encode(*uniform_events(args.events, rng), False),
        "real+aps+imu": encode(*real_events(args.events, rng), True),
    }
    print(f"decode of {args.events:,} events in {CHUNK_BYTES >> 10} KiB chunks, median of {args.repeats}, one thread")
    print(f"{'stream':<14} {'kernel':<9} {'words/event':>11} {'M events/s':>11} {'M words/s':>10} "
          f"{'x real time':>11}")
    for name, words in streams.items():
        data = words.tobytes()
        for label, fn, repeats in (("decoder", run, args.repeats),
                                   ("numpy-ref", run_numpy_reference, max(1, args.repeats // 2))):
            sec, n_ev, n_words, span_s = fn(data, repeats)
            print(f"{name:<14} {label:<9} {n_words / n_ev:>11.2f} "
                  f"{n_ev / sec / 1e6:>11.1f} {n_words / sec / 1e6:>10.1f} {span_s / sec:>11.1f}")


if __name__ == "__main__":
    main()
