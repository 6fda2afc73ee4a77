"""The `latency` mode of tools/bench_stream.py: a paced replay through the full node, with each frame's latency
from the arrival of its last event to its sending (at the publisher) and to its receipt (at the subscriber)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from drivers.pacing import MAX_GAP_US, MAX_LATE_S
from tools.stream_harness import recording_stats, run_with_subscriber


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
    a deblurred frame its exposure end), relative to the fastest frame of each stretch the replay paced on one
    schedule (the subscriber does not know when the replay clock started). A new schedule begins where sensor time
    jumps back (a loop restarts), where it jumps ahead by more than the pacer replays as a pause (drivers.pacing:
    the jump is skipped), and where a frame comes more than the pacer's MAX_LATE_S later than the one before
    on the previous schedule (the pacer, that far behind, restarts its schedule instead of catching up: measured
    against the old one, one stall would count in every later frame)."""
    recv_ns, t_us = arrivals[:, 0].astype(np.float64), arrivals[:, 1].astype(np.float64)
    offset = recv_ns / 1e3 - t_us / speed  # paced: wall µs = start + (t - t0) / speed
    dt = np.diff(t_us)
    restarts = (dt < -2e5) | (dt > MAX_GAP_US) | (np.diff(offset) > MAX_LATE_S * 1e6)
    out = np.empty_like(offset)
    for seg in np.split(np.arange(offset.size), np.flatnonzero(restarts) + 1):
        if seg.size:
            out[seg] = offset[seg] - offset[seg].min()
    return out


def _print_outside_latency(arrivals: np.ndarray | None, speed: float) -> None:
    if arrivals is None or not len(arrivals):
        return
    lat = outside_latency_us(arrivals, speed) / 1000
    deblurred = arrivals[:, 2].astype(bool)
    print("seen from the subscriber (receive time - paced wall time of the frame's last event / exposure end, "
          "relative to the fastest frame of each schedule the pacer kept: a pass, or from a restart after a stall):")
    for kind, sel in (("latent", ~deblurred), ("deblurred", deblurred)):
        if sel.any():
            q = np.percentile(lat[sel], [50, 90, 99, 100])
            print(f"  {kind:9s} frames {int(sel.sum()):6d}: p50 {q[0]:.3f} ms, p90 {q[1]:.3f} ms, p99 {q[2]:.3f} ms, "
                  f"max {q[3]:.3f} ms")
