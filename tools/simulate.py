"""Command line of the DAVIS simulator (the package edi_live.simulation): writes OUT.aedat4 (events + APS
frames, IMU optional) and OUT.npz (ground truth, including the true camera) beside it.

    python -m tools.simulate OUT.aedat4 [--preset demo] [--resolution 240x180] [--effect flicker] ...

The Python API lives in `edi_live.simulation` (`SceneConfig`, `preset()`, `simulate()`, ...); the names are
re-exported here for the tools that use them.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from edi_live.errors import EdiLiveError
from edi_live.simulation import (EFFECTS, PRESETS, PROCEDURAL_TEXTURES, RESOLUTIONS, SKIMAGE_TEXTURES,  # noqa: F401
                                 SceneConfig, Simulation, load_ground_truth, make_texture, preset,
                                 save_ground_truth, simulate, with_effects, write_aedat4)


def _parse_pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be two comma-separated numbers, e.g. 200,50") from None
    return a, b


def _help_epilog() -> str:
    """Where the defaults come from: the preset's settings over SceneConfig's, both listed from the code."""
    base = SceneConfig()
    shown = ("width", "height", "duration_s", "texture", "seed", "c_on", "c_off", "c_sigma", "velocity_px_s",
             "rotation_deg_s", "zoom_per_s", "oscillation_period_s", "exposure_us", "frame_interval_us",
             "refractory_us", "noise_rate_hz", "hot_pixels", "hot_rate_hz", "aps_noise_dn", "aps_offset_dn",
             "aps_gamma", "event_offset_us", "latent_per_interval", "shot_noise_hz", "flicker_hz", "flicker_depth")
    lines = ["defaults: an option not given takes its value from --preset (default demo), else from these",
             "(units in the names: _s seconds, _us microseconds, _hz per second, _px_s pixels per second, c in",
             "log-intensity units):",
             textwrap.fill(", ".join(f"{k}={getattr(base, k)}" for k in shown), 100, initial_indent="  ",
                           subsequent_indent="  "), "", "presets:"]
    for name in sorted(PRESETS):
        lines.append(textwrap.fill(", ".join(f"{k}={v}" for k, v in PRESETS[name].items()), 100,
                                   initial_indent=f"  {name}: ", subsequent_indent="      "))
    lines += ["", "camera effects (--effect NAME, repeatable, or --effect all; each off unless named; an option",
              "given explicitly wins over the effect's value):"]
    for eff in EFFECTS.values():
        lines.append(textwrap.fill(f"{eff.what}. Source: {eff.source}.", 100, initial_indent=f"  {eff.name}: ",
                                   subsequent_indent="      "))
    lines += ["", "examples:", "  python -m tools.simulate /tmp/demo.aedat4",
              "  python -m tools.simulate /tmp/cam.aedat4 --preset davis346 --c 0.3 --noise-rate-hz 0.5",
              "  python -m tools.simulate /tmp/long.aedat4 --preset fast --duration-s 10 --no-ground-truth",
              "  python -m tools.simulate /tmp/lamp.aedat4 --preset translate --effect flicker --flicker-hz 120",
              "  python -m tools.simulate /tmp/real.aedat4 --preset realistic"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tools.simulate", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Simulate a DAVIS recording (events + blurry APS frames) of a moving texture; writes "
                    "OUT.aedat4 and the ground truth OUT.npz beside it.", epilog=_help_epilog())
    ap.add_argument("out", help="output .aedat4 path")
    ap.add_argument("--preset", default="demo", choices=sorted(PRESETS))
    ap.add_argument("--resolution", choices=sorted(RESOLUTIONS), help="240x180 (DAVIS240) or 346x260 (DAVIS346)")
    ap.add_argument("--duration-s", type=float)
    ap.add_argument("--texture", help=f"{', '.join(PROCEDURAL_TEXTURES + SKIMAGE_TEXTURES)} "
                                      "(scikit-image ones need the test extra)")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--c", type=float, help="contrast threshold for ON and OFF")
    ap.add_argument("--c-on", type=float)
    ap.add_argument("--c-off", type=float)
    ap.add_argument("--c-sigma", type=float, help="per-pixel threshold mismatch (log units)")
    ap.add_argument("--velocity", type=lambda s: _parse_pair(s, "--velocity"), metavar="VX,VY",
                    help="translation in px/s")
    ap.add_argument("--rotation-deg-s", type=float)
    ap.add_argument("--zoom-per-s", type=float)
    ap.add_argument("--oscillation-period-s", type=float, help="0 = constant velocity")
    ap.add_argument("--exposure-us", type=int)
    ap.add_argument("--frame-interval-us", type=int)
    ap.add_argument("--refractory-us", type=int)
    ap.add_argument("--noise-rate-hz", type=float, help="background events per pixel per second")
    ap.add_argument("--hot-pixels", type=int)
    ap.add_argument("--hot-rate-hz", type=float)
    ap.add_argument("--aps-noise-dn", type=float, help="Gaussian read noise of the APS (DN)")
    ap.add_argument("--aps-offset-dn", type=float, help="dark offset of the APS (DN)")
    ap.add_argument("--aps-gamma", type=float, help="APS response gamma (1 = linear)")
    ap.add_argument("--event-offset-us", type=int, help="shift every event timestamp (DVS/APS misalignment)")
    ap.add_argument("--shot-noise-hz", type=float, help="extra background rate per pixel in the dark")
    ap.add_argument("--flicker-hz", type=float, help="a lamp flickering at this frequency (0 = none)")
    ap.add_argument("--flicker-depth", type=float, help="the lamp's modulation depth (0..1)")
    ap.add_argument("--effect", action="append", default=[], choices=sorted(EFFECTS) + ["all"], metavar="NAME",
                    help=f"switch on a realistic camera effect: {', '.join(EFFECTS)} or all (repeatable)")
    ap.add_argument("--latent-per-interval", type=int)
    ap.add_argument("--gt-times-us", type=lambda v: tuple(int(x) for x in v.split(",")), metavar="T1,T2,...",
                    help="extra ground-truth times, µs after the start")
    ap.add_argument("--imu", action="store_true", help="also write an IMU stream")
    ap.add_argument("--no-ground-truth", action="store_true", help="do not write OUT.npz")
    args = ap.parse_args(argv)

    over: dict = {}
    if args.resolution:
        over["width"], over["height"] = RESOLUTIONS[args.resolution]
    simple = {"duration_s": args.duration_s, "texture": args.texture, "seed": args.seed, "c_sigma": args.c_sigma,
              "rotation_deg_s": args.rotation_deg_s, "zoom_per_s": args.zoom_per_s,
              "oscillation_period_s": args.oscillation_period_s, "exposure_us": args.exposure_us,
              "frame_interval_us": args.frame_interval_us, "refractory_us": args.refractory_us,
              "noise_rate_hz": args.noise_rate_hz, "hot_pixels": args.hot_pixels, "hot_rate_hz": args.hot_rate_hz,
              "aps_noise_dn": args.aps_noise_dn, "latent_per_interval": args.latent_per_interval,
              "aps_offset_dn": args.aps_offset_dn, "aps_gamma": args.aps_gamma,
              "event_offset_us": args.event_offset_us, "shot_noise_hz": args.shot_noise_hz,
              "flicker_hz": args.flicker_hz, "flicker_depth": args.flicker_depth,
              "velocity_px_s": args.velocity, "gt_extra_us": args.gt_times_us}
    over.update({k: v for k, v in simple.items() if v is not None})
    if args.c is not None:
        over["c_on"] = over["c_off"] = args.c
    if args.c_on is not None:
        over["c_on"] = args.c_on
    if args.c_off is not None:
        over["c_off"] = args.c_off
    if args.imu:
        over["imu"] = True
    if args.no_ground_truth:
        over["ground_truth"] = False
    out = Path(args.out)
    if out.is_dir() or not out.resolve().parent.is_dir():  # say so now, not after the simulation
        print(f"simulate.py: error: cannot write {out}: "
              f"{'it is a directory' if out.is_dir() else 'its folder does not exist'}", file=sys.stderr)
        return 2
    truth = out.with_suffix(".npz")
    if not args.no_ground_truth and (truth.is_dir() or truth == out):
        print(f"simulate.py: error: cannot write the ground truth {truth}: "
              f"{'it is a directory' if truth.is_dir() else 'it would replace the recording (name it .aedat4)'}",
              file=sys.stderr)
        return 2
    try:
        cfg = preset(args.preset, effects=tuple(args.effect), **over)
        sim = simulate(cfg)
    except ValueError as exc:
        print(f"simulate.py: error: {exc}", file=sys.stderr)
        return 2
    try:
        write_aedat4(sim, out)
    except EdiLiveError as exc:  # e.g. no write permission
        print(f"simulate.py: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    if not args.no_ground_truth:
        try:
            save_ground_truth(sim, truth)
        except OSError as exc:  # e.g. the disk filled up: the recording is written, the ground truth is not
            print(f"simulate.py: error: cannot write the ground truth {truth} ({exc.strerror or exc}); the "
                  f"recording {out} is complete", file=sys.stderr)
            return 1
    print(f"{out}: {cfg.width}x{cfg.height}, {cfg.duration_s:g} s, {sim.events.size} events "
          f"({int(sim.is_noise.sum())} noise), {len(sim.frames)} APS frames "
          f"(exposure {cfg.exposure_us} µs every {cfg.frame_interval_us} µs), c_on={cfg.c_on:g} c_off={cfg.c_off:g}, "
          + (f"effects: {', '.join(cfg.effects)}, " if cfg.effects else "") +
          f"simulated in {sim.wall_s:.1f} s"
          + ("" if args.no_ground_truth else f"; ground truth in {out.with_suffix('.npz')}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
