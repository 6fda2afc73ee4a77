"""The viewer's files: an MP4 (mp4v) and PNG stills of the frames it shows (`python -m tools.viewer --mp4/--png`).

A saved frame is never overwritten and never left half-written; frames the MP4 cannot take (another size than its
first) are warned about once and counted.
"""

from __future__ import annotations

import itertools
import logging
import os
from pathlib import Path

import cv2
import numpy as np

from edi_live.errors import EdiLiveError

log = logging.getLogger("edi-live-viewer")
MP4_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv")
"""Names OpenCV writes an mp4v video under (.txt fails at the first frame, .png writes something else)."""


def to_u8(image: np.ndarray) -> np.ndarray:
    """Display-ready 8 bits, gray (h, w) or colour (h, w, 3) BGR as received: u2 keeps its top byte, floats are
    clipped to 0..255."""
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return np.clip(np.nan_to_num(image), 0, 255).astype(np.uint8)


class Recorder:
    """MP4 (mp4v) and/or PNG output. The MP4 size is fixed by the first frame; other sizes are skipped."""

    def __init__(self, mp4: Path | None, png_dir: Path | None, fps: float) -> None:
        self.mp4, self.png_dir, self.fps = mp4, png_dir, fps
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.written = 0
        self.skipped_size = 0
        self._png_renamed = False
        if png_dir is not None:
            try:
                png_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise EdiLiveError(f"cannot create the --png folder {png_dir}: {exc.strerror}") from exc
        if mp4 is not None:  # cv2 opens the file only at the first frame: check the place now, not minutes later
            folder = mp4.resolve().parent
            if mp4.is_dir() or not folder.is_dir() or not os.access(folder, os.W_OK):
                why = "is a directory" if mp4.is_dir() else f"folder {folder} is missing or not writable"
                raise EdiLiveError(f"cannot write --mp4 {mp4}: {why}")
            if mp4.suffix.lower() not in MP4_SUFFIXES:
                raise EdiLiveError(f"cannot write --mp4 {mp4}: the name must end in {', '.join(MP4_SUFFIXES)} "
                                   "(OpenCV picks the container by it)")

    def write(self, header: dict, image: np.ndarray) -> None:
        shown = to_u8(image)  # gray or BGR: PNG keeps either as it is, the MP4 is always BGR
        if self.png_dir is not None:
            self._write_png(header["seq"], shown)
        if self.mp4 is not None:
            size = (shown.shape[1], shown.shape[0])
            if self._writer is None:
                self._writer = cv2.VideoWriter(str(self.mp4), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, size)
                if not self._writer.isOpened():
                    # the folder was checked at start: what is left is the size (a side of 1 pixel, a huge one)
                    raise EdiLiveError(f"cannot open {self.mp4} for MP4 (mp4v) writing of {size[0]}x{size[1]} frames "
                                       f"(the size of frame {header['seq']}, the first: OpenCV's encoder refused it)")
                self._size = size
            if size != self._size:
                if not self.skipped_size:
                    log.warning("frame %s is %dx%d, the MP4 is %dx%d: frames of another size are left out of it "
                                "(counted in the summary)", header["seq"], *size, *self._size)
                self.skipped_size += 1
                return
            self._writer.write(shown if shown.ndim == 3 else cv2.cvtColor(shown, cv2.COLOR_GRAY2BGR))
        self.written += 1

    def _write_png(self, seq: int, shown: np.ndarray) -> None:
        """frame_SEQ.png, or frame_SEQ_2.png, _3, ... when that name is taken (an earlier recording in the folder,
        or a publisher restarted: its seq starts again): a saved frame is never overwritten."""
        ok, png = cv2.imencode(".png", shown)
        if not ok:
            raise EdiLiveError(f"cannot encode frame {seq} as PNG")
        for copy in itertools.count(1):
            path = self.png_dir / (f"frame_{seq:09d}.png" if copy == 1 else f"frame_{seq:09d}_{copy}.png")
            try:
                fh = open(path, "xb")
            except FileExistsError:
                if not self._png_renamed:
                    self._png_renamed = True
                    log.warning("%s exists (an earlier recording, or the publisher restarted): frames whose name "
                                "is taken are saved as frame_SEQ_2.png, _3, ...", path)
                continue
            except OSError as exc:
                raise EdiLiveError(f"cannot write {path}: {exc.strerror or exc}") from exc
            try:
                with fh:
                    fh.write(png.tobytes())
            except OSError as exc:  # a full disk: no truncated PNG among the good ones
                path.unlink(missing_ok=True)
                raise EdiLiveError(f"cannot write {path}: {exc.strerror or exc}") from exc
            break

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
