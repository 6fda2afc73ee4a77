"""How well the cached c holds: feeds recordings through `EdiReconstructor` as the worker does (events as they
arrive via on_events, each APS frame with every event from its exposure start up to now) and prints, per frame,
the c in use, whether the fit test kept it or c was re-estimated, and the fit test's costs.

    python -m tools.measure_cached_c [FILE.aedat4 ...] [--loops 3] [--sim] [--quiet]

Without files: the three real DAVIS346 recordings (../shared/data/real relative to the repo) and, with --sim, a
simulated scene with constant c (tools/simulate.py, preset "demo").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from edi_live.reconstructor import EdiReconstructor

REAL_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"


def _frames_and_events(path: Path, loops: int):
    """(events, frames) of `loops` back-to-back copies of a recording, times shifted as --loop does."""
    from drivers.replay import merged_packets
    evs, frames = [], []
    offset = 0
    for _ in range(loops):
        span: dict = {}
        for packet in merged_packets(path, time_offset_us=offset, span=span):
            if packet.events.size:
                evs.append(packet.events)
            frames.extend(packet.frames)
        offset += span["t_last"] - span["t_first"] + 1
    return np.concatenate(evs), frames


def run(events: np.ndarray, frames: list, width: int, height: int, *, chunk: int = 2000,
        verbose: bool = True, label: str = "", **rec_kwargs) -> dict:
    """Feed events and frames in time order; returns the per-frame c trajectory and re-estimation flags."""
    # the fit test on every frame (it is what this tool prints), not thinned once the calibration has settled
    rec = EdiReconstructor(width, height, **{"settled_check_every": 1, **rec_kwargs})
    t = events["t"]
    fed = 0
    cs, flags, infos = [], [], []
    for frame in frames:
        end = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
        while fed < end:
            nxt = min(fed + chunk, end)
            rec.on_events(events[fed:nxt])
            fed = nxt
        start = int(np.searchsorted(t, frame.exposure_start_us, side="left"))
        before = rec.reestimations
        rec.on_frame(frame, events[start:fed])
        rec.settle()  # this frame's c decision (its c applies from the next frame on)
        re = rec.reestimations > before
        cs.append(rec.c_on)
        flags.append(re)
        info = dict(getattr(rec, "last_fit", None) or {})
        infos.append(info)
        if verbose:
            extra = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in info.items())
            print(f"  {label} frame {len(cs) - 1:3d} n_exp={end - start:7d} c={rec.c_on:.4f} "
                  f"{'RE-EST' if re else 'kept  '} ignored={int(rec.events_ignored)} {extra}")
    cs_a = np.array(cs)
    return {"c": cs_a, "reestimated": np.array(flags), "infos": infos, "reestimations": rec.reestimations,
            "frames": len(frames)}


def summary(name: str, res: dict) -> str:
    c = res["c"][1:] if res["c"].size > 1 else res["c"]
    return (f"{name}: re-estimations {res['reestimations']}/{res['frames']} frames; c first/median/min/max/last "
            f"{res['c'][0]:.3f}/{np.median(c):.3f}/{c.min():.3f}/{c.max():.3f}/{res['c'][-1]:.3f}")


def simulated(c: float = 0.2, c_after: float | None = None, duration_s: float = 1.5, seed: int = 0):
    """Events and frames of the 'demo' simulator preset; with c_after, the threshold jumps at half time."""
    from tools.simulate import preset, simulate
    cfg = preset("demo", c_on=c, c_off=c, duration_s=duration_s, ground_truth=False, seed=seed)
    sim = simulate(cfg)
    if c_after is None:
        return sim.events, sim.frames, cfg.width, cfg.height
    import dataclasses
    sim2 = simulate(dataclasses.replace(cfg, c_on=c_after, c_off=c_after, t0_us=cfg.t0_us + int(duration_s * 1e6)))
    ev = np.concatenate([sim.events, sim2.events])
    return ev, sim.frames + sim2.frames, cfg.width, cfg.height


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--loops", type=int, default=1, help="play each file this many times back to back")
    ap.add_argument("--sim", action="store_true", help="also a simulated scene (constant c, then a jump)")
    ap.add_argument("--quiet", action="store_true", help="summaries only")
    args = ap.parse_args(argv)
    files = args.files or sorted(REAL_DIR.glob("*.aedat4"))
    lines = []
    for path in files:
        for loops in sorted({1, args.loops}):
            ev, frames = _frames_and_events(path, loops)
            h, w = frames[0].image.shape
            name = f"{path.name} x{loops}"
            print(name)
            res = run(ev, frames, w, h, verbose=not args.quiet, label=path.stem[:8])
            lines.append(summary(name, res))
    if args.sim:
        for label, kw in (("sim demo c=0.2", dict(c=0.2)), ("sim demo c=0.2 -> 0.35", dict(c=0.2, c_after=0.35))):
            ev, frames, w, h = simulated(**kw)
            print(label)
            res = run(ev, frames, w, h, verbose=not args.quiet, label="sim")
            lines.append(summary(label, res))
    print()
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
