"""Cost of the per-pixel noise statistics (edi_live.pixel_noise) at 240x180 and 346x260: the update per APS frame
pair (one pass over the pixels; no per-event work: the counts come from the c estimator's frame pairs) and the
summary's refresh (every 25 pairs, and on every stats call during the first 50: what is timed here).

    python -m tools.bench_pixel_noise [--repeats 50]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from edi_live.pixel_noise import PixelNoise


def measure(width: int, height: int, repeats: int) -> tuple[float, float]:
    """(median ms per update, median ms per summary) on Poisson counts and APS frames with 1 DN read noise."""
    rng = np.random.default_rng(0)
    noise = PixelNoise(width, height)
    n_on, n_off = rng.poisson(0.05, width * height), rng.poisson(0.05, width * height)
    b = rng.uniform(0, 255, (height, width)).astype(np.float32)
    b2 = b + rng.normal(0, 1, b.shape).astype(np.float32)
    mask = np.zeros((height, width), bool)
    noise.update(n_on, n_off, b, b2, 40_000, mask)  # compiles or loads the kernel
    up, summ = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        noise.update(n_on, n_off, b, b2, 40_000, mask)
        t1 = time.perf_counter()
        noise.summary()
        t2 = time.perf_counter()
        up.append(t1 - t0)
        summ.append(t2 - t1)
    return 1e3 * float(np.median(up)), 1e3 * float(np.median(summ))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=40, help="at most 49: later summaries are not refreshed")
    args = ap.parse_args(argv)
    for w, h in ((240, 180), (346, 260)):
        update_ms, summary_ms = measure(w, h, args.repeats)
        print(f"{w}x{h}: update {update_ms:.3f} ms per APS frame pair, summary refresh {summary_ms:.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
