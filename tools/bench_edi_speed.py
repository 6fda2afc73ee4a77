"""Speed of the EDI core on one core: deblur per APS frame (fixed c, with c estimation, cached c) and latent
update throughput. Synthetic data: 240x180, ~200k events in a 20 ms exposure, frames every 40 ms.

    python -m tools.bench_edi_speed [--events 200000] [--repeats 15] [--no-numba]

Prints medians. --no-numba runs the numpy fallback (sets EDI_LIVE_NO_NUMBA before importing edi_live).
"""

from __future__ import annotations

import argparse
import os
import time


def synthetic(rng, np, event_dtype, width, height, n_events, t0, t1):
    """Events on ~60% of the pixels, a few per pixel; each pixel goes up 4 thresholds, then down 4, and so on
    (like edges passing back and forth), so intensities stay bounded over many frames."""
    ev = np.zeros(n_events, event_dtype)
    ev["t"] = np.sort(rng.integers(t0, t1, n_events))
    ev["x"] = rng.integers(0, width, n_events)
    ev["y"] = rng.integers(0, int(height * 0.6), n_events)
    idx = ev["y"].astype(np.int64) * width + ev["x"]
    order = np.argsort(idx, kind="stable")
    sorted_idx = idx[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_idx)) + 1]
    rank = np.arange(n_events) - np.repeat(starts, np.diff(np.r_[starts, n_events]))
    p = np.empty(n_events, bool)
    p[order] = (rank // 4) % 2 == 0
    ev["p"] = p
    return ev


def median_ms(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return 1e3 * times[len(times) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=200_000, help="events per 20 ms exposure")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--no-numba", action="store_true", help="measure the numpy fallback")
    args = ap.parse_args()
    if args.no_numba:
        os.environ["EDI_LIVE_NO_NUMBA"] = "1"
    import numpy as np

    import edi_live.edi as edi
    from edi_live.datatypes import EVENT_DTYPE, Frame
    from edi_live.reconstructor import EdiReconstructor

    w, h, n = args.width, args.height, args.events
    rng = np.random.default_rng(0)
    period, exposure, c_true = 40_000, 20_000, 0.25
    n_frames = 3 + args.repeats
    # one consistent synthetic stream: each B follows the EDI model from a random latent image, so the c
    # estimator has a true answer (c_true) and the cached-c fit test can pass
    log_l0 = np.log(rng.uniform(40, 100, (h, w)))
    batches = []
    for k in range(n_frames):
        ts = k * period
        inside = synthetic(rng, np, EVENT_DTYPE, w, h, n, ts, ts + exposure)
        between = inside.copy()  # the same pixels with the opposite polarity: every period ends where it began
        between["p"] = ~inside["p"]
        between["t"] = np.sort(rng.integers(ts + exposure + 1, ts + period, n))
        batches.append((inside, between))
    frames = []
    log_l = log_l0.copy()  # latent at the previous f
    f_prev = 0
    for k, (inside, between) in enumerate(batches):
        ts = k * period
        f = ts + exposure // 2
        both = np.concatenate([*batches[k - 1], inside]) if k else inside
        log_l = log_l + edi.event_delta(both, w, h, c_true, t0=f_prev + 1, t1=f)
        table = edi.build_level_table(inside, w, h, ts, ts + exposure, f)
        log_b = log_l.copy()
        log_b.reshape(-1)[table.pixels] += edi.log_divisor(table, c_true)
        frames.append(Frame(np.clip(np.exp(log_b), 0, 255).round().astype(np.uint8), ts, ts + exposure, seq=k))
        f_prev = f

    def run(rec, k):
        inside, between = batches[k]
        t = time.perf_counter()
        rec.on_frame(frames[k], inside)
        dt = time.perf_counter() - t
        rec.on_events(between)
        return dt

    def frame_cost(**kw):
        rec = EdiReconstructor(w, h, **kw)
        for k in range(3):  # warm-up (numba compile, first estimate)
            run(rec, k)
        times = sorted(run(rec, k) for k in range(3, n_frames))
        return 1e3 * times[len(times) // 2], rec

    table = edi.build_level_table(batches[0][0], w, h, 0, exposure)
    b, informative = edi.blurry_to_float(frames[0].image)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores (other processes skew timings)")
    print(f"edi-live EDI speed, {w}x{h}, {n:,} events in a {exposure / 1000:.0f} ms exposure "
          f"({table.n_active:,} active pixels, {table.n_levels:,} levels), numba={'on' if edi.have_numba() else 'off'}")
    build_ms = median_ms(lambda: edi.build_level_table(batches[0][0], w, h, 0, exposure, segments=False),
                         args.repeats)
    eval_ms = median_ms(lambda: edi.log_divisor(table, 0.25), args.repeats)
    deblur_ms = median_ms(lambda: edi.deblur_log(b, table, 0.25, informative=informative), args.repeats)
    print(f"  level table build                     {build_ms:8.2f} ms")
    print(f"  one c evaluation (all active pixels)  {eval_ms:8.2f} ms")
    print(f"  deblur_log (one c, incl. evaluation)  {deblur_ms:8.2f} ms")
    fast_ms = median_ms(lambda: edi.log_divisor_events(batches[0][0], w, h, 0, exposure, None, 0.25), args.repeats)
    print(f"  one-pass divisor for a known c        {fast_ms:8.2f} ms")
    fixed_ms, _ = frame_cost(c=0.25)
    print(f"  on_frame, fixed c                     {fixed_ms:8.2f} ms   (target <= 1.5 ms)")
    est_ms, rec = frame_cost(reestimate_every=1)
    print(f"  on_frame, c estimated every frame     {est_ms:8.2f} ms   (target <= 5 ms; "
          f"{rec.reestimations} estimations, c = {rec.c_on:.3f}, true {c_true})")
    cached_ms, rec = frame_cost()
    print(f"  on_frame, cached c + fit test         {cached_ms:8.2f} ms   ({rec.reestimations} estimations in "
          f"{rec.frames} frames, c = {rec.c_on:.3f})")
    rec = EdiReconstructor(w, h, c=0.25)
    run(rec, 0)
    stream = synthetic(rng, np, EVENT_DTYPE, w, h, 1_000_000, 30_000, 39_000)
    stream["t"] += n_frames * period
    for batch in (1_000, 10_000, 100_000):
        chunks = [stream[i:i + batch] for i in range(0, stream.size, batch)]
        t = time.perf_counter()
        for c in chunks:
            rec.on_events(c)
        dt = time.perf_counter() - t
        print(f"  latent update, batches of {batch:>7,}   {stream.size / dt / 1e6:8.1f} M events/s   "
              f"(target >= 20)")
    render_ms = median_ms(rec.render, args.repeats * 10)
    print(f"  render() (uint8 copy)                 {render_ms * 1e3:8.1f} µs")


if __name__ == "__main__":
    main()
