"""Which c estimator recovers the simulated c best? Prints per-scene errors and a summary.

    python -m tests.edi_live.compare_estimators      # from the repository root

Scenes from the test fixture edi_scenes.py (80x60, 4 APS frames, 8 ms exposures every 20 ms, threshold
mismatch sigma 0.02): 4 textures x 2 c values x 2 velocities. The consistency estimator uses the 3 frame pairs
jointly; the energy estimator (single frame) is scored on frames 2-4.
"""

from __future__ import annotations

import time

import numpy as np

import edi_live.contrast as contrast
from tests.edi_live.edi_scenes import make_scene
from tests.edi_live.test_contrast import pairs_of


def main() -> None:
    scenes = []
    for tex in ("brick", "camera", "grass", "gravel"):
        for c in (0.15, 0.3):
            for v in ((0.5, 0.2), (1.0, -0.4)):
                scenes.append((tex, c, v, make_scene(tex, c_on=c, velocity_px_per_ms=v, width=80, height=60,
                                                     n_frames=4, sigma_c=0.02, seed=len(scenes))))
    estimators = {
        "consistency (default)": contrast.ConsistencyContrast(),
        "energy lambda=0.5": contrast.EnergyContrast(lam=0.5),
        "energy lambda=1": contrast.EnergyContrast(lam=1.0),
        "energy lambda=2": contrast.EnergyContrast(lam=2.0),
    }
    print(f"{'estimator':24s} {'mean |err|':>10s} {'max |err|':>10s} {'within 0.03':>12s} {'ms/estimate':>12s}")
    for name, est in estimators.items():
        errs, times, misses = [], [], []
        for tex, c, v, sc in scenes:
            frames, pairs = pairs_of(sc)
            jobs = [(frames[-1], pairs)] if est.needs_pair else [(fd, []) for fd in frames[1:]]
            for fd, prs in jobs:
                t = time.perf_counter()
                found = est.estimate(fd, prs, (0.2, 0.2))
                times.append(time.perf_counter() - t)
                errs.append(abs(found[0] - c) if found else np.inf)
                if errs[-1] > 0.03:
                    misses.append(f"{tex} c={c} v={v}: {found[0] if found else None}")
        errs = np.array(errs)
        print(f"{name:24s} {errs.mean():10.4f} {errs.max():10.4f} {np.mean(errs <= 0.03):11.0%} "
              f"{1e3 * np.median(times):12.2f}")
        if est.needs_pair:
            for miss in misses:
                print(f"    miss: {miss}")


if __name__ == "__main__":
    main()
