"""One reconstructor option against the default, on both simulated suites: the mean PSNR at mid-exposure (f) and on
latent frames of the 7 ideal moving scenes (tools/accuracy_harness.scene_suite, the moving ones) and of the 5
realistic-camera mixes (tools/bench_realistic, scored in the camera's tone), each scene run with and without it.

    python -m tools.bench_option latent_denoise=true [--quick]

KEY is a field of edi_live.reconstructor_settings.ReconstructorSettings, VALUE a Python or TOML literal (true,
false, numbers). Prints a row per scene and the means with the difference.
"""

from __future__ import annotations

import argparse
import ast
import sys

import numpy as np

from edi_live.simulation import simulate
from tools.accuracy_harness import run_reconstructor, scene_suite, score
from tools.bench_realistic import in_camera_tone, realistic_suite


def parse_setting(text: str) -> tuple[str, object]:
    """'key=value' -> (key, value), value as a Python literal (true/false as in TOML)."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise SystemExit(f"bench_option: expected KEY=VALUE (got {text!r})")
    raw = {"true": "True", "false": "False"}.get(raw.strip().lower(), raw.strip())
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        value = raw
    return key.strip(), value


def compare(option: dict, quick: bool = False, log=print) -> dict[str, tuple[float, float, float, float]]:
    """Per suite: (f without, f with, latent without, latent with), means over its scenes."""
    suites = {
        "ideal": [(label, cfg, False) for label, cfg in scene_suite(quick) if not label.startswith("static")],
        "realistic": [(label, cfg, True) for group, label, cfg in realistic_suite(quick) if group == "mix"],
    }
    means = {}
    for name, scenes in suites.items():
        rows = []
        for label, cfg, tone in scenes:
            sim = simulate(cfg)
            truth = in_camera_tone(sim) if tone else sim
            base, with_it = score(truth, run_reconstructor(sim)), score(truth, run_reconstructor(sim, **option))
            rows.append((base.psnr_deblur, with_it.psnr_deblur, base.psnr_latent, with_it.psnr_latent))
            log(f"{name:9s} {label[:34]:34s} f {rows[-1][0]:6.2f} -> {rows[-1][1]:6.2f}   latent {rows[-1][2]:6.2f} "
                f"-> {rows[-1][3]:6.2f}")
        means[name] = tuple(float(np.mean([r[k] for r in rows])) for k in range(4))
    return means


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_option", description=__doc__.split("\n")[0])
    ap.add_argument("setting", nargs="+", help="KEY=VALUE of ReconstructorSettings")
    ap.add_argument("--quick", action="store_true", help="the short suites")
    args = ap.parse_args(argv)
    option = dict(parse_setting(s) for s in args.setting)
    means = compare(option, args.quick)
    print(f"\n{option}: mean PSNR (dB), default -> with it")
    print("| suite | f | latent |\n|---|---:|---:|")
    for name, (f0, f1, l0, l1) in means.items():
        print(f"| {name} | {f0:.2f} → {f1:.2f} ({f1 - f0:+.2f}) | {l0:.2f} → {l1:.2f} ({l1 - l0:+.2f}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
