"""The `--out` and `--record` sink threads: AEDAT4 files written beside the live pipeline.

- `OutWriter` ("out-writer"): every reconstruction the worker emits, as an 8-bit gray (or, from a colour camera,
  BGR: DV's colour frame format) AEDAT4 frame whose timestamp and exposure start/end all equal the latent time t,
  frame source "reconstruction". AEDAT4 streams must be in time order, but in causal mode a deblurred frame
  (t = mid-exposure f) is emitted after latent frames that are newer than f: edi_live.frame_order puts them back
  in order (a frame is written once it is `reorder_us` behind the newest frame and not newer than the newest
  reference time seen); a frame older than one already written (possible only past the bound on held frames) is
  counted (`out_late`).
- `RecordWriter` ("record-writer"): the raw input packets as received (events, APS frames, IMU, triggers),
  for later `--replay`; a colour camera's raw mosaics keep their Bayer pattern (frame-stream metadata).
  Items that would go back in time in their stream are skipped and counted.

Both are lossless: `submit()` waits when the bounded queue is full (the wait is counted in `wait_s`), they are
finalised (FileDataTable written) by `close()`, on stop and after faults alike, and a failure is handed to
`on_error` (the node's fail()) naming the thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable

from edi_live.datatypes import ColorFilter, Frame, Packet, Reconstruction
from edi_live.errors import NodeError
from edi_live.frame_order import FrameOrder
from edi_live.ring import as_events

log = logging.getLogger(__name__)

_STOP = object()
_DEFAULT_REORDER_US = 100_000
_MAX_HELD_FRAMES = 2048


class _SinkThread:
    """A bounded queue drained by one thread that owns an open AEDAT4 writer."""

    def __init__(self, name: str, open_writer: Callable[[], Any], queue_items: int = 256,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        self.name = name
        self._open_writer = open_writer
        self._queue: queue.Queue = queue.Queue(maxsize=queue_items)
        self._on_error = on_error
        self._thread: threading.Thread | None = None
        self._writer: Any = None
        self.error: BaseException | None = None
        self.items = 0
        self.wait_s = 0.0  # time producers spent waiting for room (the cost of losslessness)

    def start(self) -> None:
        """Open the file on the calling thread (so a bad path fails at start), then start the thread."""
        self._writer = self._open_writer()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> None:
        """Lossless hand-over: wait for room, but never on a dead thread."""
        try:
            self._queue.put_nowait(item)
            return
        except queue.Full:
            pass
        start = time.monotonic()
        try:
            while self.error is None and self._thread is not None and self._thread.is_alive():
                try:
                    self._queue.put(item, timeout=0.1)
                    return
                except queue.Full:
                    continue
        finally:
            self.wait_s += time.monotonic() - start

    def _run(self) -> None:
        try:
            while True:
                item = self._queue.get()
                if item is _STOP:
                    break
                self._write(item)
                self.items += 1
            self._finish()
        except BaseException as exc:
            self.error = exc
            log.debug("%s failed", self.name, exc_info=True)
            if self._on_error is not None:
                self._on_error(exc)
        finally:
            try:
                self._writer.close()  # finalise whatever was written, after faults too
            except BaseException as exc:  # a fault while finalising (a full disk, the file gone from its path)
                if self.error is None:
                    self.error = exc
                    if self._on_error is not None:
                        self._on_error(exc)

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued, finalise the file and join. NodeError if the thread does not finish in time."""
        if self._thread is None:
            return
        if self._thread.is_alive():
            self._put(_STOP)
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise NodeError(f"the {self.name} thread did not finish writing within {timeout_s:.0f} s "
                                f"(disk too slow?); its file may be incomplete")

    def _write(self, item: Any) -> None:  # runs on the writer thread
        raise NotImplementedError

    def _finish(self) -> None:  # runs on the writer thread before close
        pass


class OutWriter(_SinkThread):
    """`--out FILE.aedat4`: every emitted reconstruction as a gray or BGR frame at its latent time."""

    def __init__(self, path: str | Path, width: int, height: int, *, camera_name: str = "edi-live",
                 queue_items: int = 256, reorder_us: int = _DEFAULT_REORDER_US,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        self.path = Path(path)

        def open_writer() -> Any:
            from edi_live.aedat4 import Aedat4Writer

            return Aedat4Writer(self.path, width, height, events=False, frames=True, camera_name=camera_name,
                                frame_source="reconstruction")

        super().__init__("out-writer", open_writer, queue_items, on_error)
        self._order = FrameOrder(reorder_us, max_held=_MAX_HELD_FRAMES)  # a file waits as long as it must
        self._late_said = False
        self.frames = 0

    @property
    def late(self) -> int:
        return self._order.late

    def submit(self, rec: Reconstruction) -> None:
        """Called by the worker (or its deblur thread: one at a time); waits if the queue is full (lossless)."""
        self._put(rec)

    def _write(self, rec: Reconstruction) -> None:
        self._order.add(rec)
        self._write_frames(self._order.ready())

    def _finish(self) -> None:
        self._write_frames(self._order.rest())

    def _write_frames(self, recs: list[Reconstruction]) -> None:
        if self._order.late and not self._late_said:
            self._late_said = True
            log.warning("--out: a frame came older than one already written (at %d µs); skipped (counted as "
                        "out_late)", self._order.released_t)
        for rec in recs:
            t = int(rec.t_us)
            self._writer.write_frame(Frame(rec.image, exposure_start_us=t, exposure_end_us=t, start_us=t, end_us=t))
            self.frames += 1

    def stats(self) -> dict[str, Any]:
        return {"out_frames": self.frames, "out_late": self.late, "out_wait_s": round(self.wait_s, 3)}


class RecordWriter(_SinkThread):
    """`--record FILE.aedat4`: the input packets as received (events, APS frames, IMU, triggers)."""

    def __init__(self, path: str | Path, width: int, height: int, *, camera_name: str = "edi-live",
                 queue_items: int = 256, on_error: Callable[[BaseException], None] | None = None,
                 color_filter: ColorFilter | None = None) -> None:
        self.path = Path(path)

        def open_writer() -> Any:
            from edi_live.aedat4 import Aedat4Writer

            return Aedat4Writer(self.path, width, height, events=True, frames=True, imu=True, triggers=True,
                                camera_name=camera_name, frame_source="aps", color_filter=color_filter)

        super().__init__("record-writer", open_writer, queue_items, on_error)
        self._last = {"events": -(2**63), "frames": -(2**63), "imu": -(2**63), "triggers": -(2**63)}
        self.events = 0
        self.frames = 0
        self.skipped = 0

    def submit(self, packet: Packet) -> None:
        """Called on the pump thread; waits if the queue is full (lossless relative to what arrived)."""
        self._put(packet)

    def _write(self, packet: Packet) -> None:
        w = self._writer
        events = self._in_order("events", as_events(packet.events))
        if len(events):
            w.write_events(events)
            self.events += len(events)
        for frame in packet.frames:
            if frame.exposure_start_us < self._last["frames"]:
                self.skipped += 1
                continue
            w.write_frame(frame)
            self._last["frames"] = frame.exposure_start_us
            self.frames += 1
        imu = self._in_order("imu", packet.imu)
        if len(imu):
            w.write_imu(imu)
        triggers = self._in_order("triggers", packet.triggers)
        if len(triggers):
            w.write_triggers(triggers)

    def _in_order(self, name: str, items: Any) -> Any:
        """The items not older than what this stream already holds (a device timestamp reset, say)."""
        if not len(items):
            return items
        t = items["t"]
        keep = t >= self._last[name]
        if len(t) > 1:
            keep[1:] &= t[1:] >= t[:-1]
        if not keep.all():
            self.skipped += int((~keep).sum())
            items = items[keep]
            if not len(items):
                return items
        self._last[name] = int(items["t"][-1])
        return items

    def stats(self) -> dict[str, Any]:
        return {"record_events": self.events, "record_frames": self.frames, "record_skipped": self.skipped,
                "record_wait_s": round(self.wait_s, 3)}
