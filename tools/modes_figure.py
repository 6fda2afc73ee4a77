"""A latent frame of each `--mode` (causal, nearest, fused) at the same time on a real recording, beside the APS
frames before and after it: what each mode shows between two APS frames. Runs the node as a user would (--out) and
reads its frames back.

    python -m tools.modes_figure docs/modes_real.png [--recording FILE.aedat4] [--between K] [--strip OUT.png]
        [--interval OUT.png [--interval-frame J]]

`--strip OUT.png`: a second picture, to look for jumps where the reference changes: for nearest and fused, the
consecutive latent frames around APS frame K+1's mid-exposure (fused switches from the pair (K, K+1) to (K+1, K+2)
there; nearest switched at the midpoint before), cropped to the moving part, each with its change from the
frame before (x4) below it.

`--interval OUT.png`: a third picture, how each mode's frames age over one APS interval: a row per mode, cropped to
the moving part, at +3, +10, +20 and +30 ms after APS frame J's exposure end and just before frame J+1's exposure
ends (causal frames come from frame J alone, so the errors of its events pile up until J+1; fused frames lean on
J+1 as they near it). It also prints, per mode, the share of speckle pixels (more than 20 DN from their 3x3 median,
tools.measure_speckle's measure) in the frames 10, 20 and 30 ms after every exposure, beside the APS frames' own.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import Frame
from tools.figure import _fit, _label, load_recording, write_rows
from tools.measure_speckle import outliers
from tools.real_camera_figure import REAL


def frames_of(path: Path) -> list[Frame]:
    with Aedat4Reader(path) as reader:
        return [item for _, item in reader if isinstance(item, Frame)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--recording", type=Path, default=REAL / "emlb_demo-01_davis346.aedat4")
    ap.add_argument("--between", type=int, default=6, help="show the time halfway between APS frames K and K+1")
    ap.add_argument("--strip", type=Path, help="also write the frames around APS frame K+1 (reference switch)")
    ap.add_argument("--every", type=int, default=300)
    ap.add_argument("--interval", type=Path, help="also write each mode's frames over one APS interval")
    ap.add_argument("--interval-frame", type=int, default=3, help="the APS frame J that interval starts at")
    args = ap.parse_args(argv)
    _, aps = load_recording(args.recording)
    k = min(args.between, len(aps) - 2)
    t = (aps[k].mid_exposure_us + aps[k + 1].mid_exposure_us) // 2
    gain = 255.0 / max(1.0, float(np.percentile(aps[k].image, 99.5)))
    tiles = [_label(aps[k].image * gain, f"APS frame {k}")]
    strips, intervals = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("causal", "nearest", "fused"):
            out = Path(tmp) / f"{mode}.aedat4"
            subprocess.run([sys.executable, "-m", "edi_live", "--replay", str(args.recording), "--speed", "0",
                            "--no-publish", "--mode", mode, "--every", str(args.every), "--out", str(out)],
                           check=True, capture_output=True)
            frames = frames_of(out)  # read once, for every picture below
            if args.interval:
                intervals.append(interval_row(frames, aps, min(args.interval_frame, len(aps) - 2), mode, gain))
                print(speckle_line(frames, aps, mode))
            if args.strip and mode != "causal":
                crop = moving_box(np.abs(aps[k + 1].image.astype(np.float64) - aps[k].image))
                strips.append(switch_strip(frames, aps[k + 1], mode, gain, crop=crop))
            # an --out frame's exposure window is its latent time; pick the one nearest the midpoint
            lo, hi = aps[k].mid_exposure_us, aps[k + 1].mid_exposure_us
            inside = [f for f in frames if lo < f.exposure_start_us < hi]
            best = min(inside, key=lambda f: abs(f.exposure_start_us - t))
            after_ms = (best.exposure_start_us - aps[k].mid_exposure_us) / 1000
            tiles.append(_label(best.image * gain, f"{mode}: APS {k} + {after_ms:.1f} ms"))
    tiles.append(_label(aps[k + 1].image * gain, f"APS frame {k + 1}"))
    write_rows([np.hstack(_fit(tiles, 200))], args.out)
    if args.strip:
        write_rows(strips, args.strip)
    if args.interval:
        print(f"APS frames: {np.mean([outliers(a.image, 20).mean() for a in aps]) * 100:.3f} % speckle pixels")
        write_rows(intervals, args.interval)
    return 0


def _nearest(video: list[Frame], t: int) -> Frame:
    return min(video, key=lambda x: abs(x.exposure_start_us - t))


def interval_row(frames: list[Frame], aps: list[Frame], j: int, mode: str, gain: float) -> np.ndarray:
    """The mode's frames at fixed times after APS frame j's exposure end, cropped to the moving part."""
    a, b = aps[j], aps[j + 1]
    y0, y1, x0, x1 = moving_box(np.abs(b.image.astype(np.float64) - a.image), margin=40)
    times = [a.exposure_end_us + dt for dt in (3000, 10000, 20000, 30000)] + [b.exposure_end_us - 500]
    tiles = []
    for t in times:
        f = _nearest(frames, t)
        ms = (f.exposure_start_us - a.exposure_end_us) / 1000
        tiles.append(_label((f.image.astype(np.float64) * gain)[y0:y1, x0:x1], f"{mode} +{ms:.1f} ms"))
    return np.hstack(_fit(tiles, 200))


def speckle_line(frames: list[Frame], aps: list[Frame], mode: str) -> str:
    """Mean share of speckle pixels in the frames 10, 20 and 30 ms after each exposure end (from the second APS
    frame to the one before the last, where every mode has frames)."""
    shares = []
    for dt in (10000, 20000, 30000):
        picked = [_nearest(frames, a.exposure_end_us + dt) for a in aps[1:-1]]
        shares.append(np.mean([outliers(f.image, 20).mean() for f in picked]) * 100)
    return f"{mode}: " + ", ".join(f"+{dt} ms {v:.3f} %" for dt, v in zip((10, 20, 30), shares)) + " speckle pixels"


def moving_box(change: np.ndarray, margin: int = 12) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) around the pixels that changed clearly (1st..99th percentile of their positions)."""
    ys, xs = np.nonzero(change > 25)
    if ys.size < 20:
        return 0, change.shape[0], 0, change.shape[1]
    (y0, y1), (x0, x1) = np.percentile(ys, [1, 99]).astype(int), np.percentile(xs, [1, 99]).astype(int)
    return max(0, y0 - margin), y1 + margin, max(0, x0 - margin), x1 + margin


def switch_strip(frames: list[Frame], switch: Frame, mode: str, gain: float, n: int = 3,
                 crop: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """n latent frames before and n after the switch frame's mid-exposure, cropped to where they change, each
    above its change from the previous frame (x4, mid-grey = none)."""
    f = switch.mid_exposure_us
    video = sorted(frames, key=lambda x: x.exposure_start_us)  # --out frames carry their time as a 0-length window
    i = next(j for j, x in enumerate(video) if x.exposure_start_us > f)
    lo, hi = max(1, i - n), min(len(video), i + n)
    imgs = [x.image.astype(np.float64) for x in video[lo - 1:hi]]
    if crop is None:
        crop = moving_box(np.abs(imgs[-1] - imgs[0]))
    y0, y1, x0, x1 = crop
    tops, bottoms = [], []
    for x, prev, cur in zip(video[lo:hi], imgs, imgs[1:]):
        ms = (x.exposure_start_us - f) / 1000
        tops.append(_label((cur * gain)[y0:y1, x0:x1], f"{mode} {ms:+.1f} ms"))
        bottoms.append(_label((128 + 4 * (cur - prev))[y0:y1, x0:x1], "change x4"))
    return np.vstack([np.hstack(_fit(tops, 120)), np.hstack(_fit(bottoms, 120))])


if __name__ == "__main__":
    raise SystemExit(main())
