"""Speckle on real recordings: how many pixels of the node's frames stand out from their 3x3 neighbourhood.

    python -m tools.measure_speckle FILE.aedat4 [FILE ...] [--after-ms 10] [--threshold 20] [--set KEY=VALUE ...]
        [--drop-unsupported noisy|all --noise-calibration CAL.json] [--drop-noisy --noise-calibration CAL.json]

A pixel is an outlier when it differs from the median of its 3x3 neighbourhood by more than `--threshold` DN
(border pixels left out). Per recording, the reconstructor (defaults, or ReconstructorSettings fields given with
--set, e.g. --set denoise_us=5000) sees every event in time order and each APS frame once its exposure is in, as
the worker hands them over; the latent frame `--after-ms` after each exposure end (from the second frame on) is
scored, and so is each APS frame itself (the sensor's own speckle). Prints the mean outlier fraction of both, and
of the latent outliers the share whose pixel had no event since the reference (inherited from the APS frame) or
only events without a neighbour event within 5 ms (isolated: likely noise).

The experiment of docs/calibration.md ("Per-pixel noise against speckle"): `--drop-unsupported noisy` takes out,
before the reconstructor sees them, the events at the noisy pixels of a saved calibration (`edi-live
--save-calibration`, per-pixel noise rates; pixel_noise.noisy_pixels) that have no neighbour event within 5 ms
before or after them (an upper bound of what deferring such events could do); `all` does that at every pixel;
`--drop-noisy` drops every event of the noisy pixels.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path
from typing import Any

import cv2
import numpy as np

import edi_live.edi as edi
from edi_live import calibration
from edi_live.pixel_noise import noisy_pixels, pooled_rate
from edi_live.reconstructor import EdiReconstructor
from tools.figure import WorkerFeed, load_recording


def outliers(image: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) bool: |v - median3x3(v)| > threshold, border pixels False."""
    img = np.asarray(image, np.uint8)
    med = cv2.medianBlur(img, 3)
    out = np.abs(img.astype(np.int16) - med.astype(np.int16)) > threshold
    out[0, :] = out[-1, :] = out[:, 0] = out[:, -1] = False
    return out


def noisy_map(cal_path: Path) -> np.ndarray:
    """(H, W) bool: the noisy pixels of a saved calibration's per-pixel noise rates."""
    noise = calibration.load(cal_path).noise
    if noise is None:
        raise SystemExit(f"measure_speckle: {cal_path} holds no per-pixel noise rates")
    sec = noise.seconds.astype(np.float64)
    counts = (noise.on_hz + noise.off_hz).astype(np.float64) * sec
    return noisy_pixels(counts, sec, pooled_rate(counts, sec), 5.0, 0.5)


def drop_events(events: np.ndarray, w: int, h: int, at: np.ndarray | None, unsupported_only: bool) -> np.ndarray:
    """`events` without those at pixels `at` ((H, W) bool; None: every pixel) that (if `unsupported_only`) have
    no neighbour event within 5 ms before or after them."""
    where = np.ones(events.size, bool) if at is None else at.reshape(-1)[events["y"].astype(np.int64) * w + events["x"]]
    if unsupported_only:
        where &= ~edi.supported_events_keep(events, w, h, 5000)
    return events[~where]


def latent_frames(path: Path, settings: dict[str, Any], after_us: int,
                  drop: tuple[np.ndarray | None, bool] | None = None) -> tuple[list, list, np.ndarray]:
    """(APS frames, [(frame index, latent image, its reference time, its time)], events) for one recording, times
    in the event clock; `drop`: (pixels, whether only unsupported events) for drop_events."""
    events, frames = load_recording(path)
    if drop is not None:
        events = drop_events(events, frames[0].image.shape[1], frames[0].image.shape[0], *drop)
    h, w = frames[0].image.shape[:2]
    feed = WorkerFeed(EdiReconstructor(w, h, **settings), events)
    out = []
    for k, frame in enumerate(frames):
        feed.frame(frame)
        if k == 0:
            continue
        latent = feed.latent(frame.exposure_end_us + after_us)
        out.append((k, latent.image, latent.ref_t_us, frame.exposure_end_us + after_us + feed.rec.clock_offset_us))
    return frames, out, events


def measure(path: Path, settings: dict[str, Any], after_us: int, threshold: float,
            drop: tuple[np.ndarray | None, bool] | None = None) -> dict[str, float]:
    frames, latents, events = latent_frames(path, settings, after_us, drop)
    h, w = frames[0].image.shape[:2]
    aps = [outliers(f.image, threshold).mean() for f in frames]
    lat, no_event, isolated = [], [], []
    t = events["t"]
    for k, image, f, t_lat in latents:
        bad = outliers(image, threshold)
        lat.append(bad.mean())
        window = events[int(np.searchsorted(t, f, side="right")):int(np.searchsorted(t, t_lat, side="right"))]
        counts = np.bincount(window["y"].astype(np.int64) * w + window["x"], minlength=w * h).reshape(h, w)
        supported = edi.supported_events_keep(window, w, h, 5000)
        sup_counts = np.bincount(window["y"][supported].astype(np.int64) * w + window["x"][supported],
                                 minlength=w * h).reshape(h, w)
        n_bad = max(int(bad.sum()), 1)
        no_event.append(float((bad & (counts == 0)).sum()) / n_bad)
        isolated.append(float((bad & (counts > 0) & (sup_counts == 0)).sum()) / n_bad)
    return {"aps_pct": 100 * float(np.mean(aps)), "latent_pct": 100 * float(np.mean(lat)),
            "no_event_share": float(np.mean(no_event)), "isolated_share": float(np.mean(isolated)),
            "frames": len(lat)}


def _setting(text: str) -> tuple[str, Any]:
    key, _, value = text.partition("=")
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return key, value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", type=Path, nargs="+")
    ap.add_argument("--after-ms", type=float, default=10.0)
    ap.add_argument("--threshold", type=float, default=20.0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a ReconstructorSettings field, e.g. denoise_us=5000 (repeatable)")
    ap.add_argument("--drop-unsupported", choices=("noisy", "all"),
                    help="drop events without a neighbour event within 5 ms, at the noisy pixels or everywhere")
    ap.add_argument("--drop-noisy", action="store_true", help="drop every event of the noisy pixels")
    ap.add_argument("--noise-calibration", type=Path, metavar="CAL.json",
                    help="a saved calibration with per-pixel noise rates: which pixels are noisy")
    args = ap.parse_args(argv)
    settings = dict(_setting(s) for s in args.set)
    drop = None
    if args.drop_unsupported == "all":
        drop = (None, True)
    elif args.drop_unsupported == "noisy" or args.drop_noisy:
        if args.noise_calibration is None:
            ap.error("--drop-unsupported noisy and --drop-noisy need --noise-calibration")
        drop = (noisy_map(args.noise_calibration), not args.drop_noisy)
        print(f"noisy pixels in {args.noise_calibration.name}: {int(drop[0].sum())}")
    print(f"settings: {settings or '(defaults)'}; latent frames {args.after_ms:g} ms after each exposure, "
          f"outliers > {args.threshold:g} DN from the 3x3 median")
    print(f"{'recording':32s} {'frames':>6s} {'APS %':>7s} {'latent %':>8s} {'no event':>8s} {'isolated':>8s}")
    for path in args.files:
        m = measure(path, settings, int(args.after_ms * 1000), args.threshold, drop)
        print(f"{path.stem:32s} {m['frames']:6d} {m['aps_pct']:7.3f} {m['latent_pct']:8.3f} "
              f"{m['no_event_share']:8.2f} {m['isolated_share']:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
