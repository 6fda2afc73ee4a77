"""What the APS black-level estimate does on the accuracy benchmark's scenes: per scene the true black level, the
value the reconstructor ends with when it estimates it (black_level=None), and its last fit (the profile's minimum,
that value corrected for the APS noise and the noise measured, the profile's z, the moving quiet pixels near the
estimate that support it, the policy's decision). Also a few variants of the camera
and blocks scenes with a 10 DN black level and read noise. Documents docs/calibration.md's black-level findings.

    python -m tools.black_level_report [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate, with_effects
from tools.accuracy_harness import scene_suite
from tools.bench_realistic import realistic_suite


def _between(ev: np.ndarray, t0: int, t1: int, left: bool) -> np.ndarray:
    t = ev["t"]
    return ev[np.searchsorted(t, t0, "left" if left else "right"):np.searchsorted(t, t1, "left")]


def estimate(cfg: SceneConfig) -> tuple[float, dict]:
    """(the black level the reconstructor ends with, its policy's last fit) on the simulated scene."""
    sim = simulate(dataclasses.replace(cfg, ground_truth=False))
    rec = EdiReconstructor(cfg.width, cfg.height, black_level=None)
    frames = sim.frames
    for k, f in enumerate(frames):
        rec.on_frame(f, _between(sim.events, f.exposure_start_us, f.exposure_end_us + 1, True))
        rec.settle()  # the black level policy runs after the frame (its value applies from the next one)
        if k + 1 < len(frames):
            rec.on_events(_between(sim.events, f.exposure_end_us, frames[k + 1].exposure_start_us, False))
    return rec._black.value, dict(rec._black.last_fit)


def scenes(quick: bool) -> list[tuple[str, SceneConfig]]:
    ideal = [(f"ideal: {label}", cfg) for label, cfg in scene_suite(quick)]
    real = [(f"{group}: {label}", cfg) for group, label, cfg in realistic_suite(quick)]
    blocks = scene_suite()[0][1]
    camera = next(cfg for _, label, cfg in realistic_suite() if label.endswith("ideal camera"))
    extra = [("ideal blocks + 10 DN", with_effects(blocks, "black_level")),
             ("camera + 10 DN + 1 DN read noise", with_effects(camera, "black_level", "read_noise")),
             ("camera + 10 DN + 2 DN read noise", dataclasses.replace(with_effects(camera, "black_level"),
                                                                      aps_noise_dn=2.0))]
    return ideal + real + extra


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the benchmark's quick scene lists")
    args = ap.parse_args(argv)
    print("| scene | true (DN) | estimate (DN) | last fit | noise-corrected | APS noise (DN) | z | support / moving | "
          "decision |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for label, cfg in scenes(args.quick):
        value, fit = estimate(cfg)
        print(f"| {label} | {cfg.aps_offset_dn:g} | {value:g} | {fit.get('black_level', '-')} | "
              f"{fit.get('corrected', '-')} | {fit.get('noise_dn', '-')} | {fit.get('z', '-')} | "
              f"{fit.get('support', '-')} / {fit.get('moving', '-')} | {fit.get('decision', '-')} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
