"""Benchmark: DAVIS USB word decode throughput (drivers.davis.decoder), numba kernel vs numpy fallback.

Builds word streams with the project's encoder, cuts them into 128 KiB USB-sized chunks and times
`DavisDecoder.decode` over all chunks on one thread. Prints the median of several runs in M events/s and
M words/s. Streams: "real" = the events of a real DAVIS346 recording (row bursts as a sensor produces them),
tiled in time; "uniform" = uniformly random addresses (worst case, ~1 timestamp word per event);
"+aps+imu" = real events plus 25 fps DAVIS346 APS frames and 1 kHz IMU samples. "x real time" = seconds of
sensor time decoded per second of wall time.

    python tools/bench_usb_decode.py [--events 4000000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make the repository importable
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.davis import _kernel  # noqa: E402
from drivers.davis.decoder import DavisDecoder  # noqa: E402
from drivers.davis.encoder import WordEncoder  # noqa: E402
from edi_live.datatypes import Frame  # noqa: E402

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


def run(data: bytes, use_numba: bool, repeats: int) -> tuple[float, int, int, float]:
    chunks = [data[i:i + CHUNK_BYTES] for i in range(0, len(data), CHUNK_BYTES)]
    times, n_ev = [], 0
    for _ in range(repeats):
        d = DavisDecoder(346, 260, use_numba=use_numba)
        t0 = time.perf_counter()
        n_ev = sum(len(d.decode(c).events) for c in chunks)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), n_ev, len(data) // 2, d.watermark_us / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=4_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    if _kernel.HAVE_NUMBA:  # compile outside the timing
        DavisDecoder(346, 260, use_numba=True).decode(encode(*uniform_events(1000, rng), False).tobytes())
    streams = {
        "real": encode(*real_events(args.events, rng), False),
        "uniform": encode(*uniform_events(args.events, rng), False),
        "real+aps+imu": encode(*real_events(args.events, rng), True),
    }
    print(f"decode of {args.events:,} events in {CHUNK_BYTES >> 10} KiB chunks, median of {args.repeats}, one thread")
    print(f"{'stream':<14} {'kernel':<6} {'words/event':>11} {'M events/s':>11} {'M words/s':>10} "
          f"{'x real time':>11}")
    for name, words in streams.items():
        data = words.tobytes()
        for use_numba in ([True] if _kernel.HAVE_NUMBA else []) + [False]:
            sec, n_ev, n_words, span_s = run(data, use_numba, args.repeats if use_numba else max(1, args.repeats // 2))
            print(f"{name:<14} {'numba' if use_numba else 'numpy':<6} {n_words / n_ev:>11.2f} "
                  f"{n_ev / sec / 1e6:>11.1f} {n_words / sec / 1e6:>10.1f} {span_s / sec:>11.1f}")


if __name__ == "__main__":
    main()
