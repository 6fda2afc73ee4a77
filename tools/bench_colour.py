"""Colour benchmark: EDI on a colour DAVIS346's Bayer mosaic against a colour ground truth, and its cost against
grey EDI on the same events.

Accuracy (per-channel PSNR and CPSNR, the PSNR over all three channels, in dB, 3 px border left out) of the
deblurred frame at f and of the latent frames between APS frames, on simulated colour scenes (edi_live.simulation
with `color_filter`), for:
- blurry: the APS mosaic, demosaiced;
- node: EdiReconstructor on the mosaic, c estimated (the default);
- oracle: the same with the true c (the colour oracle);
- demosaic+grey: the baseline "demosaic, then grey EDI per channel": each demosaiced channel deblurred by grey EDI
  with the true c and every pixel's events (what a grey EDI does when handed a colour camera's frames);
- node, BGR input: the node fed demosaiced BGR frames, which it re-mosaics with the source's pattern.
Every method is given the true APS response and clock offset; only c differs between node and oracle.

Also: the demosaicing methods (CPSNR of the node's output with each, and their cost as a ratio to bilinear), c per
channel against one shared c (edi_live.colour_edi.channel_contrast), and the cost of colour against grey EDI with
the same event count (deblur per APS frame, latent frames every 1000 events), as ratios measured alternately in one
run: median, min and max over the repeats (CPU time of this thread; the machine is shared).

    python -m tools.bench_colour            # two DAVIS346-sized scenes, about a minute of CPU
    python -m tools.bench_colour --quick    # smaller and shorter
    python -m tools.bench_colour --speed 1000 3000 10000   # only the latent-frame cost ratios at these
        # events per frame, with the compiled demosaic, then with OpenCV's (5 repeats unless --repeats; colour
        # and grey alternate within each repeat)
    python -m tools.bench_colour --node 1000    # the whole node's CPU, colour against grey (below)
    python -m tools.bench_colour --floor 1000   # the latent-frame ratio with the demosaic replaced by stand-ins
        # that do no arithmetic (below)

`--floor EVERY`: what the latent-frame ratio would be with a free demosaic. The demosaic is replaced by (a) a
function that returns one preallocated (h, w, 3) array (no output written at all: a lower bound no real demosaic
reaches) and (b) a copy of that array into a new one (the 270 kB output written, no arithmetic): the cost of the
colour frame's size alone, against grey frames of a third of the bytes.

`--node EVERY`: the node as a user runs it (replay at --speed 0, one subscriber receiving every frame, each run in a
fresh process) on one simulated 346x260 recording whose raw mosaic is stored without its pattern, read once as
grey and once as colour (`--bayer-pattern RGGB`): the same events and frames, alternating, node CPU seconds.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from edi_live.colour import DEMOSAIC_METHODS, demosaic, mosaic  # noqa: E402
from edi_live.colour_edi import channel_contrast  # noqa: E402
from edi_live.datatypes import Frame  # noqa: E402
from edi_live.reconstructor import EdiReconstructor  # noqa: E402
from edi_live.simulation import SceneConfig, Simulation, simulate, with_effects  # noqa: E402

cv2.setNumThreads(1)
BORDER = 3
METHODS = ("blurry", "node", "oracle", "demosaic+grey", "node, BGR input")


def scenes(quick: bool) -> dict[str, SceneConfig]:
    size = dict(width=160, height=120, duration_s=0.35) if quick else dict(width=346, height=260, duration_s=0.6)
    base = SceneConfig(**size, texture="blocks", color_filter="RGGB", velocity_px_s=(300.0, 60.0), seed=3)
    return {"blocks, ideal camera": base,
            "astronaut, realistic camera": with_effects(dataclasses.replace(
                base, texture="astronaut", texture_anchor="centre", velocity_px_s=(200.0, 50.0), seed=4), "all")}


def channel_psnr(img: np.ndarray, ref: np.ndarray) -> tuple[list[float], float]:
    """([PSNR of B, G, R], CPSNR) in dB, both on 0..255 after clipping, without the border."""
    a = np.clip(np.asarray(img, np.float64), 0, 255)[BORDER:-BORDER, BORDER:-BORDER]
    b = np.clip(np.asarray(ref, np.float64), 0, 255)[BORDER:-BORDER, BORDER:-BORDER]
    to_db = lambda mse: 10 * math.log10(255.0 ** 2 / max(mse, 1e-12))  # noqa: E731
    return [to_db(float(np.mean((a[..., k] - b[..., k]) ** 2))) for k in range(3)], to_db(float(np.mean((a - b) ** 2)))


def _windows(sim: Simulation):
    """(frame index, frame, its events since the previous exposure end) in order."""
    lo = -(2 ** 62)
    for i, f in enumerate(sim.frames):
        t = sim.events["t"]
        yield i, f, sim.events[(t > lo) & (t <= f.exposure_end_us)]
        lo = f.exposure_end_us


def _camera(cfg: SceneConfig) -> dict:
    return dict(black_level=cfg.aps_offset_dn, aps_gamma=cfg.aps_gamma, clock_offset_us=cfg.event_offset_us)


class GreyPerChannel:
    """The baseline: demosaic the APS frame, then one grey EDI per channel with every pixel's events."""

    def __init__(self, sim: Simulation, method: str):
        cfg = sim.config
        self.pattern, self.method = cfg.color_filter, method
        self.recs = [EdiReconstructor(cfg.width, cfg.height, c_on=cfg.c_on, c_off=cfg.c_off, **_camera(cfg))
                     for _ in range(3)]

    def on_frame(self, frame: Frame, events: np.ndarray) -> np.ndarray:
        bgr = demosaic(frame.image, self.pattern, self.method)
        return np.dstack([r.on_frame(dataclasses.replace(frame, image=np.ascontiguousarray(bgr[..., k]),
                                                         color_filter=None), events).image
                          for k, r in enumerate(self.recs)])

    def latent(self, t_us: int, events: np.ndarray) -> np.ndarray:
        return np.dstack([r.render_from_reference(t_us, events).image for r in self.recs])


def accuracy(sim: Simulation, method: str) -> dict:
    """{method: {"f": [(psnr_b, psnr_g, psnr_r, cpsnr)...], "latent": [...]}} and the node's per-channel c test."""
    cfg = sim.config
    pattern = cfg.color_filter
    colour = dict(color_filter=pattern, demosaic=method, **_camera(cfg))
    # the node's frames do not depend on it here, but channel_contrast reads every pair's level tables, which a
    # settled node builds only where its thinned fit test needs them
    runners = {"node": EdiReconstructor(cfg.width, cfg.height, settled_check_every=1, **colour),
               "oracle": EdiReconstructor(cfg.width, cfg.height, c_on=cfg.c_on, c_off=cfg.c_off, **colour),
               "node, BGR input": EdiReconstructor(cfg.width, cfg.height, **colour)}
    grey = GreyPerChannel(sim, method)
    scores: dict = {m: {"f": [], "latent": []} for m in METHODS}
    gt_t = sim.gt_t_us
    for i, frame, events in _windows(sim):
        mid = frame.mid_exposure_us
        gt = sim.gt_at(mid)
        scores["blurry"]["f"].append(channel_psnr(demosaic(frame.image, pattern, method), gt))
        outs = {"node": runners["node"].on_frame(frame, events).image,
                "oracle": runners["oracle"].on_frame(frame, events).image,
                "node, BGR input": runners["node, BGR input"].on_frame(
                    Frame(demosaic(frame.image, pattern, method), frame.exposure_start_us, frame.exposure_end_us),
                    events).image,
                "demosaic+grey": grey.on_frame(frame, events)}
        for m, img in outs.items():
            scores[m]["f"].append(channel_psnr(img, gt))
        if i + 1 >= len(sim.frames):
            continue
        nxt = sim.frames[i + 1]
        span = sim.events[(sim.events["t"] > frame.exposure_start_us) & (sim.events["t"] <= nxt.exposure_end_us)]
        for t in gt_t[(sim.gt_kind == 1) & (sim.gt_frame == i)]:
            gt = sim.gt_at(int(t))
            scores["blurry"]["latent"].append(channel_psnr(demosaic(frame.image, pattern, method), gt))
            for m in ("node", "oracle", "node, BGR input"):
                scores[m]["latent"].append(channel_psnr(runners[m].render_from_reference(int(t), span).image, gt))
            scores["demosaic+grey"]["latent"].append(channel_psnr(grey.latent(int(t), span), gt))
    node = runners["node"]
    per_channel = channel_contrast(node.estimator, node.pairs, pattern, cfg.height, cfg.width, (node.c_on, node.c_off))
    return {"scores": scores, "channels": per_channel, "c": (node.c_on, node.c_off)}


def _mean_row(rows: list) -> list[float]:
    return [float(np.mean([r[0][k] for r in rows])) for k in range(3)] + [float(np.mean([r[1] for r in rows]))]


def demosaic_costs(shape: tuple[int, int], repeats: int) -> dict[str, float]:
    """CPU µs per demosaic of a random mosaic of `shape` (median of repeats)."""
    raw = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    out = {}
    for m in DEMOSAIC_METHODS:
        times = []
        for _ in range(repeats):
            t0 = time.thread_time()
            for _ in range(20):
                demosaic(raw, "RGGB", m)
            times.append((time.thread_time() - t0) / 20 * 1e6)
        out[m] = float(np.median(times))
    return out


def speed(sim: Simulation, repeats: int, every: int = 1000) -> dict[str, tuple[float, float, float]]:
    """Colour / grey cost ratios (median, min, max over repeats) of the deblur per APS frame and of latent frames
    every `every` events, on the same events; grey reads the same mosaic as a grey frame."""
    cfg = sim.config
    grey_frames = [dataclasses.replace(f, color_filter=None) for f in sim.frames]

    def run(frames, colour: bool, gray: bool = False) -> tuple[float, float, int]:
        rec = EdiReconstructor(cfg.width, cfg.height, c=0.2, color_filter=cfg.color_filter if colour else None,
                               gray=gray)
        t_deblur = t_latent = 0.0
        n_latent = 0
        for i, f, events in _windows(dataclasses.replace(sim, frames=frames)):
            t0 = time.thread_time()
            rec.on_frame(f, events)
            t_deblur += time.thread_time() - t0
            after = events[events["t"] > f.exposure_end_us]
            nxt = sim.frames[i + 1].exposure_end_us if i + 1 < len(sim.frames) else None
            between = sim.events[(sim.events["t"] > f.exposure_end_us)
                                 & (sim.events["t"] <= (nxt if nxt is not None else sim.events["t"][-1]))]
            if after.size or between.size == 0:
                continue
            cuts = list(range(every, between.size + 1, every))
            t0 = time.thread_time()
            rec.on_events_frames(between, cuts, [0] * len(cuts))
            t_latent += time.thread_time() - t0
            n_latent += len(cuts)
        return t_deblur, t_latent, n_latent

    ratios: dict[str, list[float]] = {"deblur": [], "latent": [], "latent, --gray": []}
    run(grey_frames, False), run(sim.frames, True)  # warm-up: numba kernels, caches
    for _ in range(repeats):
        g_deblur, g_latent, _ = run(grey_frames, False)
        c_deblur, c_latent, _ = run(sim.frames, True)
        _, gray_latent, _ = run(sim.frames, True, gray=True)
        ratios["deblur"].append(c_deblur / g_deblur)
        ratios["latent"].append(c_latent / g_latent)
        ratios["latent, --gray"].append(gray_latent / g_latent)
    return {k: (float(np.median(v)), float(min(v)), float(max(v))) for k, v in ratios.items()}


def speed_table(everies: list[int], repeats: int) -> None:
    """Colour / grey latent-frame cost at each events-per-frame: `speed` with the compiled demosaic, then with
    OpenCV's (each ratio from colour and grey runs alternating within a repeat)."""
    import edi_live.colour as colour

    sim = simulate(scenes(False)["blocks, ideal camera"])
    compiled = colour.have_numba
    print("| events per latent frame | colour / grey, compiled | colour / grey, OpenCV | --gray / grey |")
    print("|---|---|---|---|")
    cell = lambda r: f"{r[0]:.2f} [{r[1]:.2f}, {r[2]:.2f}]"  # noqa: E731
    try:
        for every in everies:
            colour.have_numba = compiled
            ours = speed(sim, repeats, every)
            colour.have_numba = lambda: False  # type: ignore[assignment]
            theirs = speed(sim, repeats, every)
            print(f"| {every} | {cell(ours['latent'])} | {cell(theirs['latent'])} | {cell(ours['latent, --gray'])} |",
                  flush=True)
    finally:
        colour.have_numba = compiled


_NODE_RUN = r"""
import json, sys
from pathlib import Path
from tools.stream_harness import run_with_subscriber
stats, sub, _, _ = run_with_subscriber(Path(sys.argv[1]), json.loads(sys.argv[2]), 0)
print(json.dumps({"cpu_s": stats["node_cpu_s"], "frames": sub.get("frames", 0)}))
"""


def floor_table(every: int, repeats: int) -> None:
    """The latent-frame ratio with the demosaic replaced by stand-ins without arithmetic (see the docstring)."""
    import edi_live.colour_edi as colour_edi

    sim = simulate(scenes(False)["blocks, ideal camera"])
    h, w = sim.config.height, sim.config.width
    kept = np.zeros((h, w, 3), np.uint8)
    stand_ins = {"the demosaic as it is": colour_edi.demosaic,
                 "returns a preallocated array (writes nothing)": lambda mosaic_u8, pattern, method: kept,
                 "copies a 270 kB array (writes the output, no arithmetic)":
                     lambda mosaic_u8, pattern, method: kept.copy()}
    print(f"| demosaic replaced by ({every} events per latent frame) | latent colour / grey |")
    print("|---|---|")
    real = colour_edi.demosaic
    try:
        for name, fn in stand_ins.items():
            colour_edi.demosaic = fn
            med, lo, hi = speed(sim, repeats, every)["latent"]
            print(f"| {name} | {med:.2f} [{lo:.2f}, {hi:.2f}] |", flush=True)
    finally:
        colour_edi.demosaic = real


def node_table(every: int, repeats: int, duration_s: float = 1.0) -> None:
    """Node CPU, colour against grey on the same recording, alternating fresh processes (see the docstring)."""
    import json
    import subprocess
    import tempfile
    from pathlib import Path

    from edi_live.simulation import preset
    from tools.colour_recording import write_with_dv_processing

    sim = simulate(dataclasses.replace(preset("colour"), duration_s=duration_s))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mosaic.aedat4"
        write_with_dv_processing(sim, path, raw=True, name_pattern=False)
        runs: dict[str, list[dict]] = {"grey": [], "colour": []}
        root = Path(__file__).resolve().parents[1]
        for _ in range(repeats):
            for kind, extra in (("grey", {}), ("colour", {"bayer_pattern": sim.config.color_filter})):
                done = subprocess.run([sys.executable, "-c", _NODE_RUN, str(path), json.dumps({"every": every, **extra})],
                                      capture_output=True, text=True, cwd=root, check=True)
                runs[kind].append(json.loads(done.stdout.strip().splitlines()[-1]))
    ratios = [c["cpu_s"] / g["cpu_s"] for g, c in zip(runs["grey"], runs["colour"])]
    grey_s = [g["cpu_s"] for g in runs["grey"]]
    print(f"node, --every {every}, {sim.events.size} events, {runs['grey'][0]['frames']} frames to the subscriber: "
          f"grey {np.median(grey_s):.2f} s node CPU; colour / grey {np.median(ratios):.2f} "
          f"[{min(ratios):.2f}, {max(ratios):.2f}] over {repeats} alternating pairs")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller, shorter scenes and fewer repeats")
    ap.add_argument("--repeats", type=int, default=None, help="timing repeats (default 7, --quick 3)")
    ap.add_argument("--speed", type=int, nargs="+", metavar="EVERY",
                    help="only the cost ratios, at these events per latent frame: compiled demosaic and OpenCV's")
    ap.add_argument("--node", type=int, metavar="EVERY", help="only the whole node's CPU, colour against grey")
    ap.add_argument("--floor", type=int, metavar="EVERY",
                    help="only the latent-frame ratio with the demosaic replaced by stand-ins without arithmetic")
    args = ap.parse_args(argv)
    if args.floor is not None:
        if args.floor < 1:
            ap.error("--floor needs events per frame >= 1")
        floor_table(args.floor, args.repeats or 5)
        return
    if args.node is not None:
        if args.node < 1:
            ap.error("--node needs events per frame >= 1")
        node_table(args.node, args.repeats or 3)
        return
    if args.speed:
        speed_table(args.speed, args.repeats or 5)
        return
    repeats = args.repeats or (3 if args.quick else 7)
    sims = {name: simulate(cfg) for name, cfg in scenes(args.quick).items()}

    print("## Demosaicing method (node output, c estimated; CPSNR dB at f / latent; cost vs bilinear)\n")
    costs = demosaic_costs((260, 346), repeats)
    print("| method | " + " | ".join(sims) + " | cost (x bilinear) |")
    print("|---|" + "---|" * (len(sims) + 1))
    results = {}
    for m in DEMOSAIC_METHODS:
        cells = []
        for name, sim in sims.items():
            res = accuracy(sim, m)
            results[(name, m)] = res
            cells.append(f"{_mean_row(res['scores']['node']['f'])[3]:.2f} / "
                         f"{_mean_row(res['scores']['node']['latent'])[3]:.2f}")
        print(f"| {m} | " + " | ".join(cells) + f" | {costs[m] / costs['bilinear']:.2f} |")
    sharp = {name: channel_psnr(demosaic(mosaic(np.clip(sim.gt_images[0], 0, 255).astype(np.uint8),
                                                sim.config.color_filter), sim.config.color_filter, "bilinear"),
                                sim.gt_images[0])[1] for name, sim in sims.items()}
    print("\n(demosaicing alone, sharp ground truth through bilinear: "
          + ", ".join(f"{k} {v:.2f} dB" for k, v in sharp.items()) + ")\n")

    from edi_live.colour import DEFAULT_DEMOSAIC
    for name in sims:
        res = results[(name, DEFAULT_DEMOSAIC)]
        print(f"## {name} ({DEFAULT_DEMOSAIC} demosaicing): PSNR B / G / R, CPSNR (dB)\n")
        print("| method | at f | latent frames |")
        print("|---|---|---|")
        for m in METHODS:
            cells = [" / ".join(f"{v:.2f}" for v in _mean_row(res["scores"][m][k])[:3])
                     + f", **{_mean_row(res['scores'][m][k])[3]:.2f}**" for k in ("f", "latent")]
            print(f"| {m} | " + " | ".join(cells) + " |")
        ch = res["channels"]
        cfg = sims[name].config
        shared = ch["shared"] or (math.nan, math.nan)
        print(f"\nc: node {res['c'][0]:.3f}/{res['c'][1]:.3f}, true {cfg.c_on}/{cfg.c_off}; on the last pairs shared "
              f"{shared[0]:.3f}/{shared[1]:.3f}, per channel: "
              + ", ".join(f"{k} {v[0]:.3f}/{v[1]:.3f} (z {ch['z'][k]:.2f})" for k, v in ch["channels"].items()
                          if v is not None)
              + f" -> {'per channel' if ch['per_channel'] else 'shared'}\n")

    name = next(iter(sims))
    print(f"## Speed, colour / grey on the same events ({name}, {repeats} repeats: median [min, max])\n")
    print("| what | colour / grey |")
    print("|---|---|")
    for k, (med, lo, hi) in speed(sims[name], repeats).items():
        print(f"| {k} | {med:.2f} [{lo:.2f}, {hi:.2f}] |")
    print("\ndemosaic cost, µs per 346x260 frame (median CPU time): "
          + ", ".join(f"{k} {v:.0f}" for k, v in costs.items()))


if __name__ == "__main__":
    main()
