"""Realistic-camera accuracy benchmark: the node on an unknown camera against an EDI that knows the true camera.

Owns the realistic scene suite (mixes of camera effects, and each effect alone on one base scene), the oracle
(true c_on/c_off, events moved back by the true clock offset, APS linearised with the true black level and
response, hot pixels masked), the node told the camera ("camera given"), the node told only the black level, as a
dark-frame measurement (`--calibrate-dark`) gives it ("measured"), and the table.

**Where the scores are taken.** By default in the camera's tone: the ground truth is the sharp scene as this
camera's APS would show it without blur and above its black level, 255 * (I / 255) ** (1 / gamma), as deblurring
benchmarks score sharp frames in the camera's output tone. The node without `--aps-gamma` writes frames in that
tone already (its c absorbs the response: on pixels without blur, response and c are exactly degenerate); the
oracle and the node given the camera deblur in linear light and write linear frames, which are put through the
true response before scoring. `--linear` scores everything in linear light instead (the truth as simulated):
then a node that does not know gamma loses the whole tone curve (about 8.7 dB for gamma 1.15).

    python -m tools.bench_realistic [--quick] [--linear]
    python -m tools.bench_accuracy --realistic [--quick] [--linear]     # the same
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from edi_live.simulation import EFFECTS, SceneConfig, Simulation, linearise_aps, preset, simulate, with_effects
from tools.accuracy_harness import Outputs, Score, _edi_on, _texture, run_blurry, run_reconstructor, score

def realistic_suite(quick: bool = False) -> list[tuple[str, str, SceneConfig]]:
    """(group, label, config): the realistic-camera scenes. 'mix': scenes with different mixes of effects (the
    means are over these); 'alone': one base scene with each effect alone, then all together."""
    d = 0.25 if quick else 0.5
    base = preset("translate", texture=_texture("camera"), velocity_px_s=(200.0, 50.0), duration_s=d, seed=21,
                  latent_per_interval=4)
    mixes = [
        ("blocks 300 px/s: thresholds, clock offset, black level",
         preset("translate", texture=_texture("blocks"), velocity_px_s=(300.0, 40.0), duration_s=d, seed=22),
         ("thresholds", "clock_offset", "black_level")),
        ("brick rotate: response, read noise, refractory, background",
         preset("rotate", texture=_texture("brick"), rotation_deg_s=90.0, duration_s=d, seed=23),
         ("response", "read_noise", "refractory", "background")),
        ("grass zoom: hot pixels, flicker, thresholds",
         preset("zoom", texture=_texture("grass"), zoom_per_s=1.0, duration_s=d, seed=24),
         ("hot_pixels", "flicker", "thresholds")),
        ("astronaut fast: clock offset, response, flicker, refractory",
         preset("fast", texture=_texture("astronaut"), velocity_px_s=(450.0, 100.0), duration_s=d, seed=25),
         ("clock_offset", "response", "flicker", "refractory")),
        ("346x260 camera: all effects",
         preset("davis346", texture=_texture("camera"), oscillation_period_s=0.0, velocity_px_s=(250.0, 60.0),
                duration_s=d, seed=26), ("all",)),
    ]
    out = [("mix", label, with_effects(cfg, *names)) for label, cfg, names in mixes]
    if quick:
        return [out[0], out[4], ("alone", "camera 200 px/s: all effects", with_effects(base, "all"))]
    out.append(("alone", "camera 200 px/s: ideal camera", base))
    out += [("alone", f"camera 200 px/s: {name} alone", with_effects(base, name)) for name in EFFECTS]
    out.append(("alone", "camera 200 px/s: all effects", with_effects(base, "all")))
    return out


def oracle_inputs(sim: Simulation) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """What an EDI that knows the true camera feeds itself: events moved back by the true clock offset with
    the hot pixels' events removed, and each APS frame linearised with the true black level and response
    (float, 0..255) beside its informative mask (neither clipped at 0 nor saturated)."""
    cam = sim.camera()
    cfg = sim.config
    ev = sim.events.copy()
    ev["t"] -= int(cam["event_offset_us"])
    if len(cam["hot_pixel_xy"]):
        hot = np.zeros((cfg.height, cfg.width), bool)
        hot[cam["hot_pixel_xy"][:, 1], cam["hot_pixel_xy"][:, 0]] = True
        ev = ev[~hot[ev["y"], ev["x"]]]
    frames = [(linearise_aps(cfg, f.image).astype(np.float32), (f.image > 0) & (f.image < 255)) for f in sim.frames]
    return ev, frames


def run_oracle_camera(sim: Simulation) -> Outputs:
    """EDI (edi_live.edi's public functions) with the true c_on/c_off on inputs corrected with the true camera."""
    cam = sim.camera()
    c_on, c_off = float(cam["c_on"]), float(cam["c_off"])
    out = Outputs(note=f"c_on={c_on:g} c_off={c_off:g}, offset {cam['event_offset_us']} µs, "
                       f"black {cam['aps_offset_dn']:g} DN, gamma {cam['aps_gamma']:g}, {len(cam['hot_pixel_xy'])} hot")
    ev, frames = oracle_inputs(sim)
    return _edi_on(sim, ev, frames, c_on, c_off, out)


def run_camera_given(sim: Simulation) -> Outputs:
    """The default node told the camera's black level, response and clock offset (--black-level, --aps-gamma,
    --clock-offset-us, or a saved calibration); c and everything else it still finds itself. The offset moves the
    node's exposure windows into the event clock; here the events are moved back instead, the same arithmetic."""
    cam = sim.camera()
    moved = dataclasses.replace(sim, events=sim.events.copy())
    moved.events["t"] -= int(cam["event_offset_us"])
    out = run_reconstructor(moved, black_level=float(cam["aps_offset_dn"]), aps_gamma=float(cam["aps_gamma"]),
                            clock_offset_us=0)
    return out


CALIBRATION_RUN_S = 1.0
"""Length of the recording a calibration is taken from (the same camera, another scene)."""


def calibration_scene(cfg: SceneConfig) -> SceneConfig:
    """The same simulated camera (every camera parameter of `cfg`) for CALIBRATION_RUN_S on another scene: the
    'camera' photograph, whose dark coat gives the black level dark pixels to be identified by, with another
    seed (so other noise, and other per-pixel draws: the simulator draws them per scene)."""
    return dataclasses.replace(cfg, texture=_texture("camera"), seed=cfg.seed + 1000, duration_s=CALIBRATION_RUN_S)


def run_calibrated(sim: Simulation, scratch: str | None = None) -> Outputs:
    """The default node started from a saved calibration of the same camera, as a second run does: a first run
    on `calibration_scene` is saved the way the node saves one at the end (`--save-calibration`: the stats map
    through calibration.from_stats, written and read back as JSON), then loaded for this scene the way
    `--calibration FILE` is (calibration.prepare, node.default_reconstructor). Nothing else is told."""
    import tempfile
    from pathlib import Path

    from edi_live import calibration
    from edi_live.config import EdiConfig
    from edi_live.datatypes import SourceInfo
    from edi_live.node import default_reconstructor
    from edi_live.reconstructor_stats import reconstructor_stats

    cfg = sim.config
    info = SourceInfo(cfg.width, cfg.height, name="simulated", serial=f"{cfg.width}x{cfg.height}")
    first = default_reconstructor(cfg.width, cfg.height, EdiConfig())
    run_reconstructor(simulate(calibration_scene(cfg)), reconstructor=first)
    cal = calibration.from_stats(info, reconstructor_stats(first), first.noise_rates())
    if cal is None:
        raise RuntimeError("the calibration run found no thresholds")
    with tempfile.TemporaryDirectory(dir=scratch) as tmp:
        path = Path(tmp) / "calibration.json"
        calibration.save(cal, path)
        edi, _ = calibration.prepare(EdiConfig(), info, path, None)
    second = default_reconstructor(cfg.width, cfg.height, edi)
    started = (f"started from c_on={second.c_on:.3f} c_off={second.c_off:.3f}, black {second.black_level:g} DN, "
               f"offset {second.clock_offset_us} µs; ")
    out = run_reconstructor(sim, reconstructor=second)
    out.note = started + out.note
    return out


def run_dark_measured(sim: Simulation) -> Outputs:
    """The default node with the black level a dark-frame measurement gives (--calibrate-dark: within 0.5 DN of
    the true one on the tests' dark frames, so the true one here); everything else it finds itself."""
    return run_reconstructor(sim, black_level=float(sim.camera()["aps_offset_dn"]))


REALISTIC_METHODS = (("blurry frame", run_blurry), ("EDI default (reconstructor)", lambda s: run_reconstructor(s)),
                     ("EDI node, black level measured", run_dark_measured),
                     ("EDI node, calibrated", run_calibrated),
                     ("EDI node, camera given", run_camera_given),
                     ("EDI oracle camera (edi.py)", run_oracle_camera))
LINEAR_OUTPUT = ("EDI node, camera given", "EDI oracle camera (edi.py)")  # they undo the response: linear frames


def run_realistic(quick: bool = False, *, linear: bool = False, log=print) -> list[tuple[str, str, dict[str, Score]]]:
    """Score blurry frame, default node and oracle on every realistic-camera scene, in the camera's tone unless
    `linear` (see the module docstring)."""
    rows = []
    for group, label, cfg in realistic_suite(quick):
        sim = simulate(cfg)
        log(f"# {label}: {sim.events.size} events ({int(sim.is_noise.sum())} noise), {len(sim.frames)} APS frames")
        truth = sim if linear else in_camera_tone(sim)
        gamma = 1.0 if linear else float(sim.camera()["aps_gamma"])
        rows.append((group, label, {name: score(truth, toned(runner(sim), gamma) if name in LINEAR_OUTPUT else
                                                runner(sim)) for name, runner in REALISTIC_METHODS}))
    return rows


def realistic_table(rows) -> str:
    """Per scene PSNR at f and latent for each method, the gaps of the default node and of the node told the camera
    to the oracle, SSIM, and the mean over the mixed scenes."""
    names = [n for n, _ in REALISTIC_METHODS]
    short = {"blurry frame": "blurry", "EDI default (reconstructor)": "default", "EDI node, calibrated": "calibrated",
             "EDI node, black level measured": "measured", "EDI node, camera given": "given",
             "EDI oracle camera (edi.py)": "oracle"}
    head = " | ".join(f"{short[n]} PSNR f | {short[n]} PSNR lat" for n in names)
    compared = ("EDI default (reconstructor)", "EDI node, black level measured", "EDI node, calibrated",
                "EDI node, camera given")
    gap_head = " | ".join(f"{short[n]} - oracle f / lat (dB)" for n in compared)
    lines = [f"| scene | {head} | {gap_head} | SSIM f {'/'.join(short[n][0] for n in names)} |",
             "|---|" + "---:|" * (2 * len(names) + len(compared) + 1)]

    def line(label, per):
        vals = " | ".join(f"{per[n].psnr_deblur:.2f} | {per[n].psnr_latent:.2f}" for n in names)
        o = per["EDI oracle camera (edi.py)"]
        gaps = " | ".join(f"{per[n].psnr_deblur - o.psnr_deblur:+.2f} / {per[n].psnr_latent - o.psnr_latent:+.2f}"
                          for n in compared)
        ss_f = "/".join(f"{per[n].ssim_deblur:.3f}" for n in names)
        return f"| {label} | {vals} | {gaps} | {ss_f} |"
    mix = [(lab, per) for g, lab, per in rows if g == "mix"]
    for label, per in mix:
        lines.append(line(label, per))
    if mix:
        mean = {n: Score(*(float(np.mean([getattr(p[n], f) for _, p in mix])) for f in
                           ("psnr_deblur", "ssim_deblur", "psnr_latent", "ssim_latent", "ms_deblur", "ms_latent")))
                for n in names}
        lines.append(line(f"**mean of the {len(mix)} mixed scenes**", mean))
    for g, label, per in rows:
        if g == "alone":
            lines.append(line(label, per))
    return "\n".join(lines)


def in_camera_tone(sim: Simulation) -> Simulation:
    """`sim` with its ground truth put through the camera's true response (black level left out)."""
    gamma = float(sim.camera()["aps_gamma"])
    if gamma == 1.0:
        return sim
    return dataclasses.replace(sim, gt_images=[tone(g, gamma) for g in sim.gt_images])


def tone(img: np.ndarray, gamma: float) -> np.ndarray:
    """Linear intensity on the 8-bit scale -> the APS tone 255 * (I / 255) ** (1 / gamma), float."""
    x = np.clip(np.asarray(img, np.float64), 0.0, None)
    return x if gamma == 1.0 else 255.0 * (x / 255.0) ** (1.0 / gamma)


def toned(out: Outputs, gamma: float) -> Outputs:
    """A linear-light method's outputs put through the response, to be scored in the camera's tone."""
    if gamma == 1.0:
        return out
    return Outputs(deblurred={g: (tone(img, gamma), ms) for g, (img, ms) in out.deblurred.items()},
                   latent={g: (tone(img, gamma), ms) for g, (img, ms) in out.latent.items()}, note=out.note)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_realistic", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 short scenes")
    ap.add_argument("--linear", action="store_true", help="score in linear light instead of the camera's tone")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run_realistic(args.quick, linear=args.linear)
    where = "linear light" if args.linear else "the camera's tone"
    print(f"\n## Realistic camera: PSNR (dB) of the blurry frame, the default node and the oracle camera, "
          f"in {where}\n")
    print(realistic_table(rows))
    print(f"\nwall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
