"""Make the README's picture: blurry APS frames beside EDI's sharp reconstruction.

Top row: a simulated DAVIS240 scene (blurry APS frame, EDI with automatic c, ground truth).
Bottom row: the real DAVIS346 Newton's-cradle recording (blurry APS frame, EDI at mid-exposure, a latent frame
later in the same frame interval). Everything goes through `EdiReconstructor` exactly as the node uses it.

    python -m tools.figure docs/blurry_vs_sharp.png [--real ../shared/data/real/emlb_demo-01_davis346.aedat4]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from drivers.replay import merged_packets
from edi_live.datatypes import EVENT_DTYPE, concat_events
from edi_live.reconstructor import EdiReconstructor
from tools.simulate import preset, simulate

DEFAULT_REAL = Path(__file__).resolve().parent.parent.parent / "shared/data/real/emlb_demo-01_davis346.aedat4"


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)
    cv2.rectangle(out, (0, 0), (tw + 8, th + 8), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (40, 220, 255), 1, cv2.LINE_AA)
    return out


def _deblur_through(frames: list, events: np.ndarray) -> tuple[EdiReconstructor, object]:
    """Feed each frame with its exposure's events to one reconstructor (c is estimated from the frame pairs);
    returns the reconstructor and the last frame's deblurred Reconstruction."""
    rec = EdiReconstructor(frames[0].width, frames[0].height)
    out = None
    for frame in frames:
        lo = np.searchsorted(events["t"], frame.exposure_start_us)
        hi = np.searchsorted(events["t"], frame.exposure_end_us, side="right")
        out = rec.on_frame(frame, events[lo:hi])
    return rec, out


def _fit(tiles: list[np.ndarray], height: int) -> list[np.ndarray]:
    return [cv2.resize(t, (t.shape[1] * height // t.shape[0], height)) for t in tiles]


def simulated_row(height: int) -> list[np.ndarray]:
    sim = simulate(preset("demo", duration_s=0.4))
    rec, deblurred = _deblur_through(sim.frames, sim.events)
    frame = sim.frames[-1]
    gt = sim.gt_at(frame.mid_exposure_us)
    tiles = [_label(frame.image, "APS frame (blurry)"), _label(deblurred.image, f"EDI, auto c={rec.c_on:.2f}"),
             _label(gt, "ground truth")]
    return _fit(tiles, height)


def load_recording(path: Path) -> tuple[np.ndarray, list]:
    """All events (time-ordered, EVENT_DTYPE) and APS frames of a recording, through the replay's merge."""
    events, frames = [], []
    for packet in merged_packets(path):
        if len(packet.events):
            events.append(np.asarray(packet.events, dtype=EVENT_DTYPE))
        frames.extend(packet.frames)
    return (concat_events(events) if events else np.zeros(0, EVENT_DTYPE)), frames


class WorkerFeed:
    """Feeds a reconstructor a recording as the worker does: every event once, in time order; each APS frame once
    the events of its window in the event clock (the clock offset in use) are in, with its calibration settled
    right after (so the offset for the next frame is known before its events are read)."""

    def __init__(self, rec: EdiReconstructor, events: np.ndarray) -> None:
        self.rec, self.events, self._t, self._fed = rec, events, events["t"], 0

    def _feed_to(self, t_us: int) -> None:
        end = max(self._fed, int(np.searchsorted(self._t, t_us, side="right")))
        self.rec.on_events(self.events[self._fed:end])
        self._fed = end

    def frame(self, frame) -> object:
        """The frame's deblurred Reconstruction."""
        off = self.rec.clock_offset_us
        self._feed_to(frame.exposure_end_us + off)
        out = self.rec.on_frame(frame, self.events[int(np.searchsorted(self._t, frame.exposure_start_us + off)):
                                                   self._fed])
        self.rec.settle()
        return out

    def latent(self, t_us: int) -> object:
        """The latent Reconstruction at APS-clock time t_us (later than everything fed so far)."""
        self._feed_to(t_us + self.rec.clock_offset_us)
        return self.rec.render()


def real_row(path: Path, height: int, frame_index: int = 3) -> list[np.ndarray]:
    ev, frames = load_recording(path)
    rec, out = _deblur_through(frames[: frame_index + 1], ev)
    frame = frames[frame_index]
    after = np.searchsorted(ev["t"], [frame.exposure_end_us, frame.exposure_end_us + 10_000], side="right")
    rec.on_events(ev[after[0]:after[1]])
    latent = rec.render()
    gain = 255.0 / max(1.0, float(np.percentile(frame.image, 99.5)))  # the recording is dark: same gain for all
    tiles = [_label(frame.image * gain, "real APS frame (blurry)"),
             _label(out.image * gain, f"EDI at mid-exposure, c={rec.c_on:.2f}"),
             _label(latent.image * gain, "EDI latent, +10 ms")]
    return _fit(tiles, height)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="PNG to write")
    ap.add_argument("--real", type=Path, default=DEFAULT_REAL, help="a real DAVIS .aedat4 with blurry frames")
    args = ap.parse_args(argv)
    height = 200
    rows = [np.hstack(simulated_row(height))]
    if args.real.is_file():
        rows.append(np.hstack(real_row(args.real, height)))
    write_rows(rows, args.out)
    return 0


def write_rows(rows: list[np.ndarray], out: Path) -> None:
    """Stack picture rows of different widths (padded with black on the right) into one PNG."""
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.vstack(rows))
    print(f"wrote {out}")


if __name__ == "__main__":
    raise SystemExit(main())
