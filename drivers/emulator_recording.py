"""What an emulated DAVIS (`drivers.emulator`) makes of the recording it plays: its sensor size, its Bayer pattern,
and its packets with every APS frame as the emulated sensor reads it (a colour sensor reads a raw mosaic).

A recording is an .aedat4 path (read through `drivers.replay.merged_packets`) or a list of `Packet`s.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator

import cv2
import numpy as np

from edi_live.datatypes import ColorFilter, Frame, Packet
from edi_live.errors import RecordingError


def is_path(recording: Any) -> bool:
    return isinstance(recording, (str, bytes)) or hasattr(recording, "__fspath__")


def as_sensor_frames(packets: Iterable[Packet], pattern: ColorFilter | None) -> Iterator[Packet]:
    """The packets with every frame as the sensor reads it: a demosaiced BGR frame becomes the raw mosaic of
    `pattern` (or, on a mono sensor, grey); a raw frame is tagged with `pattern`."""
    for p in packets:
        if p.frames:
            p = Packet(p.events, [_sensor_frame(f, pattern) for f in p.frames], p.imu, p.triggers, p.watermark_us,
                       p.arrival_ns, p.gap)
        yield p


def _sensor_frame(f: Frame, pattern: ColorFilter | None) -> Frame:
    img = f.image
    if img.ndim == 3:
        img = _mosaic(img, pattern) if pattern else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return Frame(img, f.exposure_start_us, f.exposure_end_us, f.start_us, f.end_us, f.seq, color_filter=pattern)


def _mosaic(bgr: np.ndarray, pattern: ColorFilter) -> np.ndarray:
    """What a sensor with `pattern` reads of a BGR image: each pixel its own channel. The simulator's reading of
    the pattern name (drivers stay apart from the EDI core's edi_live.colour)."""
    from edi_live.simulation.colour_scene import sensor_channels

    chan = sensor_channels(pattern, bgr.shape[0], bgr.shape[1]).astype(np.intp)
    return np.ascontiguousarray(np.take_along_axis(bgr, chan[..., None], axis=2)[..., 0])


def recording_color_filter(recording: Any) -> ColorFilter | None:
    """The Bayer pattern a recording stands for: its own (file metadata or tagged frames), RGGB (the DAVIS346
    colour's) for demosaiced BGR frames, else None (mono)."""
    if is_path(recording):
        from edi_live.aedat4.reader import Aedat4Reader
        with Aedat4Reader(recording) as r:
            first = next((f for _, _, f in r.records(("FRME",))), None)
            frames = [first] if first is not None else []
            pattern = r.source_info.color_filter
    else:
        frames = [f for p in recording if isinstance(p, Packet) for f in p.frames][:1]
        pattern = frames[0].color_filter if frames else None
    return pattern or ("RGGB" if frames and frames[0].image.ndim == 3 else None)


def recording_factory(recording: Any, on_fault: Callable[[RecordingError], None]) -> Callable[[], Iterable[Packet]]:
    if is_path(recording):
        from drivers.replay import merged_packets  # the replay engineer's reader: time-ordered packets

        def packets() -> Iterator[Packet]:
            # A damaged file ends the stream like its end would, so the word stream still sends everything
            # before the fault (held back until then); the camera then reports the fault (bulk_read).
            try:
                yield from merged_packets(recording)
            except RecordingError as exc:
                on_fault(exc)

        return packets
    packets = list(recording)
    return lambda: packets


def recording_size(recording: Any) -> tuple[int, int] | None:
    """(width, height): from the file header, or for in-memory packets from a frame or the event extent."""
    if is_path(recording):
        from edi_live.aedat4.reader import Aedat4Reader
        with Aedat4Reader(recording) as r:
            return r.source_info.width, r.source_info.height
    packets = [p for p in recording if isinstance(p, Packet)]
    for p in packets:
        if p.frames:
            return p.frames[0].width, p.frames[0].height
    xs = [int(p.events["x"].max()) for p in packets if len(p.events)]
    ys = [int(p.events["y"].max()) for p in packets if len(p.events)]
    if not xs:
        return None
    fits240 = max(xs) < 240 and max(ys) < 180
    return (240, 180) if fits240 else (max(346, max(xs) + 1), max(260, max(ys) + 1))
