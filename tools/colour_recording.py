"""A colour DAVIS346 recording written by dv-processing (the reference AEDAT4 writer) from the simulator, and the
node's accuracy when it reads that file rather than the simulation in memory.

There is no real colour recording in this project. This is the nearest stand-in: a simulated colour scene (the
`colour` preset unless told otherwise) is written by dv-processing's own MonoCameraWriter the way DV records a colour
DAVIS346, with demosaiced BGR frames (`--raw` writes the raw mosaic with a `colorFilter` stream attribute instead),
and the ground truth goes beside it (OUT.npz). With `--score`, the file is read back through edi-live's AEDAT4
reader and deblurred by the node's reconstructor (c estimated), and the deblurred frames are scored against the
ground truth (CPSNR, dB, 3 px border left out), next to the same reconstructor fed the simulation in memory (raw
mosaic) and the blurry frames.

    python -m tools.colour_recording colour.aedat4 --score
    edi-live --replay colour.aedat4          # the node on it, end to end
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from edi_live.aedat4 import Aedat4Reader
from edi_live.colour import demosaic
from edi_live.datatypes import Frame
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import Simulation, preset, save_ground_truth, simulate

BORDER = 3
CAMERA = "DAVIS346COLOR_00000000"


def write_with_dv_processing(sim: Simulation, path: Path, raw: bool = False, name_pattern: bool = True) -> None:
    """Events and APS frames of `sim` in time order through dv-processing's MonoCameraWriter: BGR frames as DV
    records a colour camera, or with `raw` the mosaic itself and its pattern as the frame stream's colorFilter
    (`name_pattern` False: not named, so that a reader takes the mosaic for a grey frame)."""
    import dv_processing as dv

    cfg = sim.config
    writer_cfg = dv.io.MonoCameraWriter.Config(CAMERA)
    writer_cfg.addEventStream((cfg.width, cfg.height))
    writer_cfg.addFrameStream((cfg.width, cfg.height))
    if raw and name_pattern:
        writer_cfg.addStreamMetadata("frames", ("colorFilter", cfg.color_filter))
    writer = dv.io.MonoCameraWriter(str(path), writer_cfg)
    ev = sim.events
    pos = 0
    for frame in [*sim.frames, None]:  # None: the events after the last frame
        end = ev.size if frame is None else int(np.searchsorted(ev["t"], frame.exposure_end_us, side="right"))
        if end > pos:
            store = dv.EventStore()
            for t, x, y, p in zip(ev["t"][pos:end].tolist(), ev["x"][pos:end].tolist(), ev["y"][pos:end].tolist(),
                                  ev["p"][pos:end].tolist()):
                store.push_back(t, x, y, p)
            writer.writeEvents(store)
            pos = end
        if frame is None:
            break
        image = frame.image if raw else demosaic(frame.image, cfg.color_filter)
        writer.writeFrame(dv.Frame(frame.exposure_start_us, frame.exposure_us, 0, 0, np.ascontiguousarray(image),
                                   dv.FrameSource.SENSOR), "frames")
    del writer  # dv-processing finalises the file (its data table) when the writer goes


def read_recording(path: Path) -> tuple[list[Frame], np.ndarray, str | None]:
    """(frames, all events, the file's Bayer pattern or None) through edi-live's reader."""
    frames, parts = [], []
    with Aedat4Reader(path) as reader:
        pattern = reader.source_info.color_filter
        for _, data in reader:
            if isinstance(data, Frame):
                frames.append(data)
            elif getattr(data, "dtype", None) is not None and data.dtype.names and "x" in data.dtype.names:
                parts.append(data)
    from edi_live.datatypes import concat_events

    return frames, concat_events(parts), pattern


def cpsnr(img: np.ndarray, ref: np.ndarray) -> float:
    a = np.clip(np.asarray(img, np.float64), 0, 255)[BORDER:-BORDER, BORDER:-BORDER]
    b = np.clip(np.asarray(ref, np.float64), 0, 255)[BORDER:-BORDER, BORDER:-BORDER]
    return 10 * math.log10(255.0 ** 2 / max(float(np.mean((a - b) ** 2)), 1e-12))


def deblurred_scores(sim: Simulation, frames: list[Frame], events: np.ndarray, pattern: str | None) -> list[float]:
    """CPSNR of the deblurred frame at each APS frame's mid-exposure, c estimated, the camera's response given."""
    cfg = sim.config
    rec = EdiReconstructor(cfg.width, cfg.height, color_filter=pattern, black_level=cfg.aps_offset_dn,
                           aps_gamma=cfg.aps_gamma, clock_offset_us=cfg.event_offset_us)
    out, lo = [], -(2 ** 62)
    for frame in frames:
        t = events["t"]
        window = events[(t > lo) & (t <= frame.exposure_end_us + cfg.event_offset_us)]
        out.append(cpsnr(rec.on_frame(frame, window).image, sim.gt_at(frame.mid_exposure_us)))
        lo = frame.exposure_end_us + cfg.event_offset_us
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.colour_recording", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="the .aedat4 to write (ground truth beside it as .npz)")
    ap.add_argument("--preset", default="colour", help="simulator preset with a colour filter (default: colour)")
    ap.add_argument("--duration-s", type=float, default=0.5)
    ap.add_argument("--raw", action="store_true", help="write the raw mosaic and its pattern instead of BGR frames")
    ap.add_argument("--score", action="store_true", help="read it back and score the node's deblurred frames")
    args = ap.parse_args(argv)
    cfg = preset(args.preset)
    if cfg.color_filter is None:
        ap.error(f"preset {args.preset!r} is monochrome; pick one with a colour filter (e.g. colour)")
    sim = simulate(dataclasses.replace(cfg, duration_s=args.duration_s))
    write_with_dv_processing(sim, args.out, raw=args.raw)
    save_ground_truth(sim, args.out.with_suffix(".npz"))
    print(f"{args.out}: {cfg.width}x{cfg.height}, {sim.events.size} events, {len(sim.frames)} "
          f"{'raw ' + cfg.color_filter if args.raw else 'BGR'} frames, written by dv-processing")
    if not args.score:
        return
    frames, events, pattern = read_recording(args.out)
    kinds = {f.image.ndim for f in frames}
    print(f"read back: {len(frames)} frames ({'BGR' if kinds == {3} else 'raw ' + str(pattern)}), "
          f"{events.size} events")
    # a BGR file names no pattern: the node assumes the DAVIS346 colour default, as the replay of such a file does
    from_file = deblurred_scores(sim, frames, events, pattern)
    in_memory = deblurred_scores(sim, sim.frames, sim.events, cfg.color_filter)
    blurry = [cpsnr(demosaic(f.image, cfg.color_filter), sim.gt_at(f.mid_exposure_us)) for f in sim.frames]
    print("CPSNR at mid-exposure, dB (mean over APS frames):")
    for name, v in (("blurry frame", blurry), ("node, dv-processing file", from_file),
                    ("node, simulation in memory", in_memory)):
        print(f"  {name:28s} {np.mean(v):6.2f}")


if __name__ == "__main__":
    main()
