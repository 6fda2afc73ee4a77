"""Before/after pictures of the real DAVIS346 recordings: the APS frame, then the deblurred frame and a latent frame 10
ms after the exposure, with the previous defaults (one c, every event trusted) and with today's (separate c_on/c_off,
events that contradict the APS frames ignored); the 3x crops also with --latent-denoise. Events reach the
reconstructor exactly as the worker hands them over (all events in time order, each APS frame once its exposure is
in).

    python -m tools.real_camera_figure docs/real_before_after.png [RECORDING ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from edi_live.reconstructor import EdiReconstructor
from tools.figure import WorkerFeed, _fit, _label, load_recording, write_rows

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
DEFAULT = [(REAL / "emlb_demo-01_davis346.aedat4", 3), (REAL / "aestream_davis346.aedat4", 2),
           (REAL / "evlib_sample_davis346.aedat4", 2)]
BEFORE = {"separate_thresholds": False, "mask_unreliable_pixels": False, "mask_flicker_pixels": False,
          "black_level": 0.0, "clock_offset_us": 0, "noise_stats": False, "divisor_median": False}


def reconstruct(events: np.ndarray, frames: list, index: int, settings: dict) -> tuple:
    """(deblurred frame `index`, latent 10 ms after its exposure end, reconstructor). Fed as the worker feeds it:
    each exposure in the event clock of the offset in use when the frame is taken."""
    rec = EdiReconstructor(frames[0].width, frames[0].height, **settings)
    feed = WorkerFeed(rec, events)
    out = None
    for frame in frames[: index + 1]:
        out = feed.frame(frame)
    return out, feed.latent(frames[index].exposure_end_us + 10_000), rec


def row(path: Path, index: int, height: int) -> np.ndarray:
    events, frames = load_recording(path)
    index = min(index, len(frames) - 1)
    frame = frames[index]
    gain = 255.0 / max(1.0, float(np.percentile(frame.image, 99.5)))  # dark recordings: one gain for the row
    tiles = [_label(frame.image * gain, f"{path.stem.split('_')[0]}: APS frame {index}")]
    for name, settings in (("before", BEFORE), ("now", {})):
        deblurred, latent, rec = reconstruct(events, frames, index, settings)
        c = f"c={rec.c_on:.2f}" if rec.c_on == rec.c_off else f"c_on={rec.c_on:.2f} c_off={rec.c_off:.2f}"
        tiles += [_label(deblurred.image * gain, f"{name}: deblurred, {c}"),
                  _label(latent.image * gain, f"{name}: latent +10 ms")]
    return np.hstack(_fit(tiles, height))


def detail(name: str, index: int, rows: slice, cols: slice, what: str, height: int) -> np.ndarray:
    """A 3x crop of one recording: the APS frame, and the latent frame 10 ms later before, now, and now with
    --latent-denoise."""
    events, frames = load_recording(REAL / name)

    def zoom(image: np.ndarray) -> np.ndarray:
        part = image[rows, cols].astype(np.uint8)
        return cv2.resize(part, (part.shape[1] * 3, part.shape[0] * 3), interpolation=cv2.INTER_NEAREST)

    tiles = [_label(zoom(frames[index].image), f"{what}, 3x: APS frame {index}")]
    for label, settings in (("before", BEFORE), ("now", {}), ("now, --latent-denoise", {"latent_denoise": True})):
        _, latent, _ = reconstruct(events, frames, index, settings)
        tiles.append(_label(zoom(latent.image), f"{label}: latent +10 ms"))
    return np.hstack(_fit(tiles, height))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="PNG to write")
    ap.add_argument("recordings", type=Path, nargs="*", help="recordings (default: the three real ones)")
    ap.add_argument("--height", type=int, default=180)
    args = ap.parse_args(argv)
    wanted = [(p, 3) for p in args.recordings] or DEFAULT
    rows = [row(p, i, args.height) for p, i in wanted]
    if not args.recordings:
        rows.append(detail("emlb_demo-01_davis346.aedat4", 3, slice(105, 175), slice(200, 340), "emlb swinging ball",
                           args.height))
        rows.append(detail("aestream_davis346.aedat4", 2, slice(0, 60), slice(150, 270), "aestream lamp", args.height))
    write_rows(rows, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
