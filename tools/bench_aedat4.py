"""Benchmark: AEDAT4 event decode throughput of edi-live's reader against dv-processing (and `aedat`) on the same
files in the same run, plus the replay merge (merged_packets) and the writer.

    python -m tools.bench_aedat4                 # the real recordings + a generated 10 M-event file
    python -m tools.bench_aedat4 --events 20000000 --repeat 7
    python -m tools.bench_aedat4 --memory 100000000   # peak memory while replaying 10^8 events
    python -m tools.bench_aedat4 --ab ../main --repeat 6   # A/B: this checkout's reader against another's

Readers take turns: in each round every reader (order rotated per round) makes a few consecutive passes (8 on
the small real files, 1 on the generated one), so each runs warm while the shared machine's slow phases hit all of
them alike. Tables show the median and the best pass in M events/s, and our/dv ratio. The process is pinned to one core (--cores 1) unless told
otherwise. Only events are decoded (other streams skipped), which is what dv-processing's getNextEventBatch does.
"walk + LZ4 only" walks the packets and decompresses the event ones without parsing them: the floor for this file.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drivers.replay import merged_packets
from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, Frame

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
REAL_FILES = ("emlb_demo-01_davis346.aedat4", "aestream_davis346.aedat4")


def ours(path: Path, validate: bool = True) -> int:
    with Aedat4Reader(path, validate=validate) as reader:
        return sum(len(ev) for ev in reader.events())


def lz4_only(path: Path) -> int:
    """The floor under any reader of this file: walk the packets and decompress the event ones, nothing else."""
    with Aedat4Reader(path) as reader:
        for _ in reader.packets(("EVTS",)):
            pass
    return -1  # counts nothing; its rate is the file's event count over its time


def dv_processing(path: Path) -> int:
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    n = 0
    while (batch := rec.getNextEventBatch()) is not None:
        n += len(batch.numpy())
    return n


def aedat_pkg(path: Path) -> int:
    import aedat

    return sum(len(p["events"]) for p in aedat.Decoder(str(path)) if "events" in p)


def replay_merge(path: Path) -> int:
    return sum(len(p.events) for p in merged_packets(path))


def generate(path: Path, n_events: int, per_packet: int = 10_000, seed: int = 0) -> float:
    """A DAVIS346-sized LZ4 file of random events in 10k-event packets with a frame every 40 ms; returns the
    writer's throughput in M events/s."""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000_000
    chunk = np.zeros(per_packet, dtype=EVENT_DTYPE)
    img = rng.integers(0, 256, (260, 346), dtype=np.uint8)
    write_s, next_frame = 0.0, t0
    with Aedat4Writer(path, 346, 260, compression="lz4") as w:
        for k in range(0, n_events, per_packet):
            m = min(per_packet, n_events - k)
            ev = chunk[:m]
            ev["t"] = t0 + (k + np.arange(m)) // 2  # 2 M events/s
            ev["x"], ev["y"] = rng.integers(0, 346, m), rng.integers(0, 260, m)
            ev["p"] = rng.random(m) < 0.5
            start = time.perf_counter()
            w.write_events(ev)
            while next_frame + 20_000 <= int(ev["t"][-1]):
                w.write_frame(Frame(img, next_frame, next_frame + 20_000))
                next_frame += 40_000
            write_s += time.perf_counter() - start
    return n_events / write_s / 1e6


def memory_run(n_events: int, tmp: str) -> None:
    """Stream a generated file of n_events through merged_packets and report the peak memory it took."""
    import resource
    import tracemalloc

    path = Path(tmp) / "memory.aedat4"
    start = time.perf_counter()
    generate(path, n_events, per_packet=50_000)
    print(f"generated {n_events:,} events ({path.stat().st_size / 1e6:,.0f} MB on disk, "
          f"{n_events * EVENT_DTYPE.itemsize / 1e6:,.0f} MB decoded) in {time.perf_counter() - start:.1f} s")
    for _ in merged_packets(path):  # warm up imports and the numba compile outside the measurement
        break
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tracemalloc.start()
    start, count, packets = time.perf_counter(), 0, 0
    for packet in merged_packets(path):
        count += len(packet.events)
        packets += 1
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(f"merged_packets: {count:,} events in {packets:,} packets, {count / seconds / 1e6:.1f} M events/s "
          f"(under tracemalloc); peak traced memory {peak / 1e6:.1f} MB; peak RSS grew by "
          f"{max(0, rss1 - rss0) / 1e3:.1f} MB")


def bench(path: Path, readers: dict, repeat: int, inner: int) -> dict[str, float]:
    """`repeat` rounds; in each, every reader (order rotated per round) makes `inner` consecutive passes, so it
    runs warm (as in real use) while slow phases of the shared machine are spread over all readers."""
    times: dict[str, list[float]] = {name: [] for name in readers}
    counts: dict[str, int] = {}
    names = list(readers)
    for k in range(repeat):
        for name in names[k % len(names):] + names[:k % len(names)]:
            fn = readers[name]
            for _ in range(inner):
                start = time.perf_counter()
                counts[name] = fn(path)
                times[name].append(time.perf_counter() - start)
    n = counts[next(iter(readers))]
    for name, c in counts.items():
        if c != n and c >= 0:
            raise SystemExit(f"{name} read {c} events from {path.name}, expected {n}")
    out = {"events": n}
    for name, ts in times.items():
        out[name] = n / statistics.median(ts) / 1e6
        out[name + " best"] = n / min(ts) / 1e6
    return out


_AB_PASSES = """
import sys, time
from edi_live.aedat4 import Aedat4Reader
def run():
    with Aedat4Reader(sys.argv[1]) as reader:
        return sum(len(ev) for ev in reader.events())
n = run(); run()
ts = []
for _ in range(int(sys.argv[2])):
    start = time.perf_counter(); run(); ts.append(time.perf_counter() - start)
print(n / sorted(ts)[len(ts) // 2] / 1e6)
"""


def ab_run(other: Path, files: list[Path], repeat: int) -> None:
    """Old vs new code path on the same files: alternating child processes (pinned to one core), each importing
    edi_live from its own checkout and reporting its median pass; prints median/min/max over the runs."""
    here = Path(__file__).resolve().parent.parent
    for path in files:
        rates: dict[str, list[float]] = {"this": [], "other": []}
        inner = "5" if path.stat().st_size > 10e6 else "15"
        for k in range(repeat):
            order = [("this", here), ("other", other)]
            for name, cwd in order if k % 2 == 0 else order[::-1]:
                cmd = [sys.executable, "-c", _AB_PASSES, str(path.resolve()), inner]
                if hasattr(os, "sched_setaffinity"):
                    cmd = ["taskset", "-c", str(min(os.sched_getaffinity(0)))] + cmd
                out = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=True)
                rates[name].append(float(out.stdout))
        cells = [f"{name} {statistics.median(v):.1f} (min {min(v):.1f}, max {max(v):.1f})" for name, v in rates.items()]
        ratio = statistics.median(rates["this"]) / statistics.median(rates["other"])
        print(f"{path.name}: M events/s over {repeat} alternating runs: {'; '.join(cells)}; this/other {ratio:.3f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=10_000_000, help="events in the generated file (default 10 M)")
    ap.add_argument("--repeat", type=int, default=5, help="rounds per file (default 5)")
    ap.add_argument("--cores", type=int, default=1, help="pin to this many cores (0 = no pinning)")
    ap.add_argument("--no-aedat", action="store_true", help="skip the aedat package")
    ap.add_argument("--memory", type=int, metavar="N", default=0,
                    help="instead: stream a generated N-event file through the replay merge and report peak memory")
    ap.add_argument("--ab", type=Path, metavar="CHECKOUT",
                    help="instead: A/B this checkout's reader against the one in CHECKOUT (another worktree)")
    args = ap.parse_args(argv)
    if args.ab:
        with tempfile.TemporaryDirectory() as tmp:
            gen = Path(tmp) / "generated.aedat4"
            generate(gen, args.events)
            ab_run(args.ab.resolve(), [REAL / n for n in REAL_FILES if (REAL / n).is_file()] + [gen], args.repeat)
        return
    if args.memory:
        with tempfile.TemporaryDirectory() as tmp:
            memory_run(args.memory, tmp)
        return
    if args.cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: args.cores])
    readers = {"ours": ours, "ours (no validation)": lambda p: ours(p, validate=False),
               "walk + LZ4 only": lz4_only, "dv-processing": dv_processing}
    if not args.no_aedat:
        readers["aedat"] = aedat_pkg
    readers["replay merge"] = replay_merge
    ours(REAL / REAL_FILES[1])  # warm up (numba compile, imports)
    print(f"cores: {len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        gen = Path(tmp) / "generated.aedat4"
        write_mevs = generate(gen, args.events)
        files = [REAL / name for name in REAL_FILES if (REAL / name).is_file()] + [gen]
        for path in files:
            inner = 1 if path == gen else 8
            rows.append((path.name, path.stat().st_size, bench(path, readers, args.repeat, inner)))
    names = list(readers)
    for label, suffix in (("median of rounds", ""), ("best round (least disturbed by other load)", " best")):
        print(f"\nM events/s, {label}:\n")
        print(f"| file | MB | events | {' | '.join(names)} | ours / dv |")
        print("|---|---:|---:|" + "---:|" * len(names) + "---:|")
        for name, size, r in rows:
            cells = " | ".join(f"{r[k + suffix]:.1f}" for k in names)
            ratio = r["ours" + suffix] / r["dv-processing" + suffix]
            print(f"| {name} | {size / 1e6:.1f} | {r['events']:,} | {cells} | {ratio:.2f} |")
    print(f"\nWriter (LZ4, generated file, 10k-event packets): {write_mevs:.1f} M events/s.")


if __name__ == "__main__":
    main()
